#pragma once
// Processes of one job (MPI ranks) as the libraries see them, without depending on MPI: the
// executable installs an MPI-backed Cluster at start-up (apps/mpi_session.cpp, built with
// -DRAYMATCH_MPI=ON); a plain process is a cluster of one. The tracer splits its ray chunks
// over the ranks and sums the integer count images with `sum`, so every rank holds the whole
// image, bit-identical to one process; only rank 0 writes files (atomic_file.h).
#include <cstddef>
#include <cstdint>
#include <functional>

namespace raymatch {

struct Cluster {
  int rank = 0;
  int size = 1;
  /// In-place sum over all ranks of `n` values (a collective: every rank calls it, in the same
  /// order). Empty for a cluster of one.
  std::function<void(uint64_t* values, size_t n)> sum;
  bool is_root() const { return rank == 0; }
};

/// The job's cluster (a cluster of one unless the executable installed another).
const Cluster& GetCluster();
/// Installs the job's cluster; call once at start-up, before any tracing.
void SetCluster(Cluster c);

}  // namespace raymatch
