#pragma once
// Exit codes shared by `compare` and `compare-scan` (OIIO idiff style, docs/compare.md).
#include <functional>
#include <iostream>

#include "raymatch/compare/measures.h"

namespace raymatch::apps {

enum CompareExit { kOk = 0, kWarn = 1, kFail = 2, kSizeMismatch = 3, kFileError = 4 };

inline int RunCompareGuarded(const std::function<int()>& fn) {
  try {
    return fn();
  } catch (const compare::CompareError& e) {
    std::cerr << "raymatch: " << e.what() << "\n";
    switch (e.kind()) {
      case compare::FailureKind::kSizeMismatch: return kSizeMismatch;
      case compare::FailureKind::kFileError: return kFileError;
      default: return kFail;
    }
  } catch (const Error& e) {
    std::cerr << "raymatch: " << e.what() << "\n";
    return kFileError;
  }
}

}  // namespace raymatch::apps
