#pragma once
// Counter-based random numbers (Random123 Philox4x32-10, Salmon et al. SC'11).
//
// Every ray owns a stream addressed by (seed, stream, ray index): the numbers a ray draws do not
// depend on which thread traces it or in what order, so images are bit-identical for any thread
// count. Each call to Next() consumes one 32-bit word; a block of four is made per Philox call.
#include <Random123/philox.h>

#include <cstdint>

namespace raymatch {

class RayRng {
 public:
  /// seed: user seed; stream: e.g. the focus-plane index; index: the ray number.
  RayRng(uint64_t seed, uint32_t stream, uint64_t index) {
    key_ = {{static_cast<uint32_t>(seed), static_cast<uint32_t>(seed >> 32)}};
    ctr_ = {{static_cast<uint32_t>(index), static_cast<uint32_t>(index >> 32), stream, 0u}};
  }
  /// The stream as if `words` words had been drawn (a fresh generator only).
  void SkipTo(uint64_t words) {
    ctr_.v[3] = static_cast<uint32_t>(words / 4);
    used_ = 4;
    if (words % 4 != 0) {
      NextU32();
      used_ = static_cast<int>(words % 4);
    }
  }
  /// Uniform in [0, 1) with 32 random bits (resolution 2^-32).
  double Uniform() { return NextU32() * 0x1p-32; }
  uint32_t NextU32() {
    if (used_ == 4) {
      block_ = philox_(ctr_, key_);
      ctr_.v[3]++;
      used_ = 0;
    }
    return block_.v[used_++];
  }

 private:
  r123::Philox4x32 philox_;
  r123::Philox4x32::key_type key_;
  r123::Philox4x32::ctr_type ctr_;
  r123::Philox4x32::ctr_type block_{};
  int used_ = 4;
};

}  // namespace raymatch
