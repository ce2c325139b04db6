// apps/epona/activity.hpp — what the program is doing now, for the one error line it prints when
// something fails without a message of its own (std::bad_alloc, a filesystem exception): a
// command names each stage ("decoding latents.npy: 4 frame(s) of 512x1024") with a scoped
// Activity, and cli.cpp prints "epona: error: <stage>: out of memory".
#pragma once

#include <exception>
#include <string>
#include <utility>

namespace epona::app {

inline std::string& current_activity() {
  thread_local std::string text;
  return text;
}

// Appends a stage to the activity for its scope ("encode" -> "encode: reading a.png") and
// restores the enclosing one after, unless an exception leaves the scope: then the stage stays
// for the handler in cli.cpp, which runs after the unwinding.
class Activity {
 public:
  explicit Activity(const std::string& what) : saved_(current_activity()), exceptions_(std::uncaught_exceptions()) {
    current_activity() = saved_.empty() ? what : saved_ + ": " + what;
  }
  Activity(const Activity&) = delete;
  Activity& operator=(const Activity&) = delete;
  ~Activity() {
    if (std::uncaught_exceptions() == exceptions_) current_activity() = std::move(saved_);
  }

 private:
  std::string saved_;
  int exceptions_;
};

}  // namespace epona::app
