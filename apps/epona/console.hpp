// apps/epona/console.hpp — where the program talks: results on stdout, notes and progress
// bars on stderr (silenced by --quiet). A progress bar redraws itself in place on a terminal
// and prints a line per tenth of the work otherwise (logs stay readable).
#pragma once

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <ostream>
#include <string>

namespace epona::app {

struct Console {
  std::ostream& out;         // results (paths written, tables)
  std::ostream& err;         // notes, progress, errors
  bool quiet = false;        // --quiet: no notes, no progress
  bool interactive = false;  // err is a terminal: progress bars redraw in place

  // A remark on stderr (what is being loaded, defaults chosen), unless quiet.
  template <class... A>
  void note(const A&... parts) const {
    if (quiet) return;
    ((err << parts), ...);
    err << "\n";
    err.flush();
  }
};

// "1 step", "2 steps": notes read as sentences.
inline std::string counted(std::int64_t n, const std::string& word) {
  return std::to_string(n) + " " + word + (n == 1 ? "" : "s");
}

// "769,476": digits grouped by thousands, as people read counts.
inline std::string grouped(std::int64_t n) {
  const std::string s = std::to_string(n < 0 ? -n : n);
  std::string out = n < 0 ? "-" : "";
  for (std::size_t i = 0; i < s.size(); ++i) {
    if (i && (s.size() - i) % 3 == 0) out += ',';
    out += s[i];
  }
  return out;
}

// "2.9 ms", "340 ms", "1.4 s", "12 s": a duration at a precision worth reading.
inline std::string duration_text(double seconds) {
  char buf[32];
  if (!(seconds >= 0)) return "-- s";
  if (seconds < 0.01)
    std::snprintf(buf, sizeof buf, "%.1f ms", seconds * 1e3);
  else if (seconds < 1)
    std::snprintf(buf, sizeof buf, "%.0f ms", seconds * 1e3);
  else if (seconds < 10)
    std::snprintf(buf, sizeof buf, "%.1f s", seconds);
  else
    std::snprintf(buf, sizeof buf, "%.0f s", seconds);
  return buf;
}

// "00:07", "12:03", "1:02:03".
inline std::string clock_text(double seconds) {
  if (!(seconds >= 0) || seconds > 1e8) return "--:--";
  const auto s = static_cast<long long>(seconds + 0.5);
  char buf[32];
  if (s >= 3600)
    std::snprintf(buf, sizeof buf, "%lld:%02lld:%02lld", s / 3600, s / 60 % 60, s % 60);
  else
    std::snprintf(buf, sizeof buf, "%02lld:%02lld", s / 60, s % 60);
  return buf;
}

// Items per second, or seconds per item when slower than one a second.
inline std::string rate_text(double items, double seconds, const std::string& unit) {
  char buf[64];
  if (items <= 0 || seconds <= 0) return "-- " + unit + "/s";
  const double per_second = items / seconds;
  if (per_second >= 1.0)
    std::snprintf(buf, sizeof buf, "%.2f %s/s", per_second, unit.c_str());
  else
    std::snprintf(buf, sizeof buf, "%.2f s/%s", seconds / items, unit.c_str());
  return buf;
}

class Progress {
 public:
  using Clock = std::chrono::steady_clock;

  Progress(const Console& console, std::string label, std::int64_t total, std::string unit)
      : console_(console), label_(std::move(label)), unit_(std::move(unit)), total_(std::max<std::int64_t>(total, 1)),
        start_(Clock::now()) {
    if (!console_.quiet && console_.interactive) draw();
  }
  Progress(const Progress&) = delete;
  Progress& operator=(const Progress&) = delete;
  ~Progress() {
    if (!finished_ && done_ > 0 && !console_.quiet && console_.interactive) console_.err << "\n";
  }

  void advance(std::int64_t n = 1) {
    done_ = std::min(total_, done_ + n);
    if (console_.quiet) return;
    if (console_.interactive) {
      draw();
    } else if (done_ == total_ || done_ * 10 / total_ > last_tenth_) {
      last_tenth_ = done_ * 10 / total_;
      console_.err << line() << "\n";
      console_.err.flush();
    }
    if (done_ == total_) finish();
  }
  double elapsed() const { return std::chrono::duration<double>(Clock::now() - start_).count(); }

  // The status line: label, bar, count, rate, elapsed, time left.
  std::string line() const {
    const int width = 24;
    const auto filled = static_cast<int>(done_ * width / total_);
    const double t = elapsed();
    std::string s = label_ + " [" + std::string(filled, '#') + std::string(width - filled, '-') + "] " +
                    std::to_string(done_) + "/" + std::to_string(total_) + " " + unit_ + "s  " +
                    rate_text(double(done_), t, unit_) + "  elapsed " + clock_text(t);
    if (done_ < total_) s += "  left " + (done_ > 0 ? clock_text(t / double(done_) * double(total_ - done_)) : "--:--");
    return s;
  }

 private:
  void draw() {
    console_.err << "\r" << line() << "\x1b[K";
    console_.err.flush();
  }
  void finish() {
    if (finished_) return;
    finished_ = true;
    if (console_.interactive) console_.err << "\n";
    console_.err.flush();
  }

  const Console& console_;
  std::string label_, unit_;
  std::int64_t total_, done_ = 0, last_tenth_ = 0;
  Clock::time_point start_;
  bool finished_ = false;
};

}  // namespace epona::app
