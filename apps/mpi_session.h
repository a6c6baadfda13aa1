#pragma once
// MPI for the raymatch executable: when built with -DRAYMATCH_MPI=ON and started by
// mpirun/srun, the ranks split each image's ray chunks and sum the integer count images
// (core/cluster.h), so `mpirun -n N raymatch simulate|run|fit|bench ...` gives the image one
// process gives with the same seed, bit for bit. Every rank runs the whole command; only rank 0
// writes into the output folder (other ranks write into a scratch folder removed at exit) and
// prints; a rank that fails prints its error and stops the job (MPI_Abort).
#include <string>

namespace raymatch::apps {

class MpiSession {
 public:
  /// Starts MPI only when launched by an MPI starter (OMPI_COMM_WORLD_SIZE, PMI_SIZE or
  /// PMIX_RANK in the environment) and the build has MPI; otherwise a cluster of one.
  MpiSession(int* argc, char*** argv);
  ~MpiSession();
  MpiSession(const MpiSession&) = delete;
  MpiSession& operator=(const MpiSession&) = delete;
};

/// The output folder this rank writes: `dir` on rank 0, a scratch folder on the others.
std::string RankOutput(const std::string& dir);

/// Prints an error message (a whole line) on stderr. On a cluster of more than one rank it then
/// stops every rank with `code`: rank 0 at once; another rank first waits a grace period in
/// which rank 0, if it fails too (bad input fails on every rank), stops the job with its own
/// message, so the message is printed once. Returns on a cluster of one.
void ReportError(const std::string& line, int code);

/// Prefix for messages: "" on a cluster of one, "rank R of N: " otherwise.
std::string RankPrefix();

/// Whether MPI support was compiled in.
bool MpiCompiledIn();

}  // namespace raymatch::apps
