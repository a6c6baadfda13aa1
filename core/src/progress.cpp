#include "raymatch/core/progress.h"

#include <algorithm>
#include <chrono>
#include <cstdio>

namespace raymatch {

Progress::Progress(bool enabled, std::string label, uint64_t total)
    : enabled_(enabled), label_(std::move(label)), total_(total) {
  if (enabled_) thread_ = std::thread([this] { Loop(); });
}

Progress::~Progress() {
  if (!enabled_) return;
  {
    std::lock_guard<std::mutex> lk(m_);
    stop_ = true;
  }
  cv_.notify_all();
  thread_.join();
  std::fprintf(stderr, "\r\033[K");
}

void Progress::Loop() {
  const auto t0 = std::chrono::steady_clock::now();
  std::unique_lock<std::mutex> lk(m_);
  // Runs shorter than ~2 s print nothing.
  if (cv_.wait_for(lk, std::chrono::seconds(2), [this] { return stop_; })) return;
  while (!stop_) {
    const double f = double(done_.load()) / double(std::max<uint64_t>(total_, 1));
    const double el = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const int w = 30, filled = static_cast<int>(f * w);
    std::fprintf(stderr, "\r%s [%.*s%*s] %5.1f%%  %.0f s elapsed, ~%.0f s left", label_.c_str(),
                 filled, "##############################", w - filled, "", 100 * f, el,
                 f > 0 ? el * (1 - f) / f : 0.0);
    std::fflush(stderr);
    cv_.wait_for(lk, std::chrono::milliseconds(500), [this] { return stop_; });
  }
}

}  // namespace raymatch
