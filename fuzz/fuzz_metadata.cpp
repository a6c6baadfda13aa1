// libFuzzer harness: experiment folders' metadata.toml, read by every reader that takes a folder:
// the light-field and flat-field calibration inputs (calibrate), the experiment (focus scan) and
// the mesh object (pipeline, as compare-scan data). The input is written as metadata.toml into
// a scratch folder holding the image names the seed corpus uses (empty files: the readers check
// that they exist, the image readers are fuzzed elsewhere).
#include "fuzz_input.h"
#include "raymatch/calibrate/inputs.h"
#include "raymatch/pipeline/pipeline.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::string dir =
      raymatch::fuzz::ScratchFolder("metadata", {{"pinhole.tif", ""},
                                                 {"dark.tif", ""},
                                                 {"cone_dz20.tif", ""},
                                                 {"cone_dz30.tif", ""},
                                                 {"flat.tif", ""},
                                                 {"flat_iris30deg.tif", ""},
                                                 {"cone_iris30deg.tif", ""},
                                                 {"scan.csv", ""},
                                                 {"merging.tif", ""},
                                                 {"merging_drops.obj", ""}});
  raymatch::fuzz::WriteInputTo(dir + "/metadata.toml", data, size);
  using raymatch::fuzz::CheckFinite;
  using raymatch::fuzz::Expect;
  Expect([&] {
    const auto in = raymatch::calibrate::ReadLightFieldInput(dir);
    for (const auto& c : in.cones) CheckFinite(c.dz_um, "cone dz_um");
    CheckFinite(in.optics.acceptance_sin(), "NA / medium_index");
  });
  Expect([&] {
    const auto in = raymatch::calibrate::ReadFlatFieldInput(dir);
    for (const auto& f : in.flats)
      CheckFinite(f.cone_dz_um * f.exposure * f.cone_exposure, "flat numbers");
  });
  Expect([&] {
    const auto e = raymatch::pipeline::ReadExperimentMetadata(dir);
    CheckFinite(e.diameter_um * e.gain, "experiment numbers");
  });
  return Expect([&] {
    const auto m = raymatch::pipeline::ReadMeshObjectMetadata(dir);
    CheckFinite(m.defocus_um + m.rotation_deg[0] + m.rotation_deg[1] + m.rotation_deg[2],
                "mesh numbers");
  });
}
