// raymatch: ray-traced image simulations of transparent objects that match microscope images.
#include <iostream>

#include "commands.h"
#include "mpi_session.h"
#include "raymatch/core/atomic_file.h"
#include "raymatch/core/error.h"
#include "raymatch/core/provenance.h"
#include "raymatch/core/version.h"
#include "raymatch/simulate/tracer.h"
#ifdef RAYMATCH_HAVE_CAPTURE
#include "raymatch/capture/camera.h"
#endif

namespace raymatch::apps {

int RunGuarded(const std::function<int()>& fn, int error_code) {
  try {
    return fn();
  } catch (const raymatch::Error& e) {
    RemoveCreatedEmptyDirectories();  // a refused input leaves no empty output folder
    ReportError(std::string("raymatch: ") + e.what() + "\n", error_code);
  } catch (const std::exception& e) {
    RemoveCreatedEmptyDirectories();
    ReportError(std::string("raymatch: error: ") + e.what() + "\n", error_code);
  }
  return error_code;
}

}  // namespace raymatch::apps

int main(int argc, char** argv) {
  raymatch::apps::MpiSession mpi(&argc, &argv);  // a cluster of one unless started by mpirun
  raymatch::SetCommandLine(argc, argv);
  CLI::App app{
      "raymatch: Monte Carlo ray-traced brightfield microscope images of transparent objects.\n"
      "Lengths are in micrometres (_um) unless a name says otherwise (_mm, _deg)."};
  // One line per build choice (CMake options RAYMATCH_MPI, RAYMATCH_WITH_MRCAL, RAYMATCH_PYTHON).
  constexpr bool kMrcal =
#ifdef RAYMATCH_HAVE_MRCAL
      true;
#else
      false;
#endif
  constexpr bool kPython =
#ifdef RAYMATCH_HAVE_PYTHON
      true;
#else
      false;
#endif
  std::string backends = "none";
#ifdef RAYMATCH_HAVE_CAPTURE
  backends.clear();
  for (const std::string& b : raymatch::capture::CompiledBackends())
    backends += (backends.empty() ? "" : ", ") + b;
#endif
  app.set_version_flag(
      "--version", std::string("raymatch ") + raymatch::kVersion + "\ncompiled-in options: MPI " +
                       (raymatch::apps::MpiCompiledIn() ? "on" : "off") + ", mrcal " +
                       (kMrcal ? "on" : "off") + ", Python module " + (kPython ? "on" : "off") +
                       "; capture backends: " + backends + "\nSIMD tracing: " +
                       raymatch::simulate::SimdTarget() + " (Google Highway, chosen at run time)");
  app.require_subcommand(1);
  int exit_code = 0;
  raymatch::apps::RegisterSimulate(app, &exit_code);
#ifdef RAYMATCH_HAVE_COMPARE
  raymatch::apps::RegisterCompare(app, &exit_code);
  raymatch::apps::RegisterCompareScan(app, &exit_code);
  raymatch::apps::RegisterProfile(app, &exit_code);
#endif
#ifdef RAYMATCH_HAVE_CALIBRATE
  raymatch::apps::RegisterCalibrate(app, &exit_code);
#endif
#ifdef RAYMATCH_HAVE_FIT
  raymatch::apps::RegisterFit(app, &exit_code);
  raymatch::apps::RegisterSensitivity(app, &exit_code);
#endif
#ifdef RAYMATCH_HAVE_CAPTURE
  raymatch::apps::RegisterCapture(app, &exit_code);
#endif
#ifdef RAYMATCH_HAVE_PIPELINE
  raymatch::apps::RegisterRun(app, &exit_code);
  raymatch::apps::RegisterBench(app, &exit_code);
#endif
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int rc = app.exit(e);
    return rc == 0 ? 0 : 2;  // 2: usage error
  }
  return exit_code;
}
