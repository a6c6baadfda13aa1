#include "raymatch/core/cluster.h"

#include <utility>

namespace raymatch {

namespace {
Cluster& Current() {
  static Cluster c;
  return c;
}
}  // namespace

const Cluster& GetCluster() { return Current(); }
void SetCluster(Cluster c) { Current() = std::move(c); }

}  // namespace raymatch
