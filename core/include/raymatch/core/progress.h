#pragma once
// A progress bar on stderr for long runs: a background thread redraws one line twice a second
// (label, bar, percentage, elapsed and remaining time) from a counter that workers add to.
#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <string>
#include <thread>

namespace raymatch {

class Progress {
 public:
  /// Nothing is shown unless `enabled`; runs shorter than about 2 s print nothing either.
  Progress(bool enabled, std::string label, uint64_t total);
  ~Progress();  ///< stops the thread and clears the line
  Progress(const Progress&) = delete;
  Progress& operator=(const Progress&) = delete;
  /// n more units of the total done (any thread).
  void Add(uint64_t n) { done_.fetch_add(n, std::memory_order_relaxed); }

 private:
  void Loop();
  bool enabled_;
  std::string label_;
  uint64_t total_;
  std::atomic<uint64_t> done_{0};
  std::thread thread_;
  std::mutex m_;
  std::condition_variable cv_;
  bool stop_ = false;
};

}  // namespace raymatch
