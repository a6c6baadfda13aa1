// libFuzzer harness: pipeline files (ReadPipelineFile, docs/pipeline.md). The input is written as
// pipeline.toml into a scratch folder holding the folders and fit file the seed corpus names
// (lightfield/, flatfield/, drop46/, merging/, fit/sphere.toml), so that a mutated file gets past
// the folder checks; names that do not exist must give a located error.
#include "fuzz_input.h"
#include "raymatch/pipeline/pipeline.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::string dir =
      raymatch::fuzz::ScratchFolder("pipeline", {{"lightfield/", ""},
                                                 {"flatfield/", ""},
                                                 {"drop46/", ""},
                                                 {"merging/", ""},
                                                 {"fit/sphere.toml", "# placeholder\n"}});
  const std::string path = dir + "/pipeline.toml";
  raymatch::fuzz::WriteInputTo(path, data, size);
  return raymatch::fuzz::Expect([&] {
    const raymatch::pipeline::PipelineFile f = raymatch::pipeline::ReadPipelineFile(path);
    raymatch::fuzz::CheckFinite(f.ray_fraction, "ray_fraction");
    raymatch::fuzz::CheckFinite(f.smoothness, "smoothness");
  });
}
