// Traces a 16x16 image of an empty scene through the installed libraries; prints the version and
// the photon count so the test can check both.
#include <iostream>

#include "raymatch/core/toml_reader.h"
#include "raymatch/core/version.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"

int main() {
  const auto scene = raymatch::simulate::LoadScene(
      raymatch::ParseTomlString(
          "name = \"c\"\n[source]\ntype = \"cone\"\nhalf_angle_deg = 20\n"
          "[objective]\nfocal_length_mm = 10\nna = 0.42\nworking_distance_mm = 20\n"
          "[tube_lens]\nfocal_length_mm = 200\n[camera]\npixels = [16, 16]\npixel_pitch_um = 20\n"
          "[trace]\nrays = 20000\n",
          "consumer.toml"),
      "consumer.toml");
  const raymatch::simulate::Simulator sim(scene);
  const auto r = sim.TracePlane(0.0, 0, 20000);
  double hits = 0;
  for (float v : r.counts.pixels) hits += v;
  std::cout << "raymatch " << raymatch::kVersion << " hits " << hits << "\n";
  return hits > 0 ? 0 : 1;
}
