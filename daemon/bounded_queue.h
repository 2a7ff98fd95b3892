// A bounded multi-producer multi-consumer queue between the pipeline's stages.
//
// Bounded because a real-time pipeline must not queue without limit when a stage falls behind:
// the producer learns at once (TryPush fails) and the frame set is counted as dropped, rather
// than latency growing until memory runs out. Slots are pre-allocated (a ring of `capacity`
// elements, moved in and out), so a push or pop allocates nothing of its own.
//
// Depth() says how full it is now and the most it ever held: a soak (bench/soak.cpp) samples the
// depths of a daemon's queues through `status`, and an instantaneous depth sampled once a second
// almost always reads 0 even when a stage falls behind for tens of milliseconds at a time; the
// high-water mark does not miss those.
#pragma once
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <mutex>
#include <utility>
#include <vector>

namespace mocap::daemon {

// A queue's fill: items now, the most it held since it was made, its capacity.
struct QueueDepth {
  std::size_t depth = 0;
  std::size_t max_depth = 0;
  std::size_t capacity = 0;
};

template <typename T>
class BoundedQueue {
 public:
  explicit BoundedQueue(std::size_t capacity) : slots_(capacity ? capacity : 1) {}

  // False (and `item` untouched) when the queue is full or closed.
  bool TryPush(T&& item) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (closed_ || size_ == slots_.size()) return false;
      slots_[(head_ + size_) % slots_.size()] = std::move(item);
      ++size_;
      if (size_ > max_size_) max_size_ = size_;
    }
    not_empty_.notify_one();
    return true;
  }

  // Waits up to `timeout` for an item. False on timeout, or when closed and drained.
  template <typename Rep, typename Period>
  bool Pop(T* item, std::chrono::duration<Rep, Period> timeout) {
    std::unique_lock<std::mutex> lock(mutex_);
    if (!not_empty_.wait_for(lock, timeout, [&] { return size_ > 0 || closed_; })) return false;
    if (size_ == 0) return false;
    *item = std::move(slots_[head_]);
    head_ = (head_ + 1) % slots_.size();
    --size_;
    return true;
  }

  // Wakes every waiting consumer; pushes fail from now on, pops drain what is left.
  void Close() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      closed_ = true;
    }
    not_empty_.notify_all();
  }

  bool closed() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return closed_;
  }
  std::size_t size() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return size_;
  }
  std::size_t capacity() const { return slots_.size(); }
  QueueDepth Depth() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return {size_, max_size_, slots_.size()};
  }

 private:
  mutable std::mutex mutex_;
  std::condition_variable not_empty_;
  std::vector<T> slots_;
  std::size_t head_ = 0;
  std::size_t size_ = 0;
  std::size_t max_size_ = 0;
  bool closed_ = false;
};

}  // namespace mocap::daemon
