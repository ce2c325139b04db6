// epona/dist/mpi_process_group.hpp — dist::ProcessGroup over MPI (MPI_COMM_WORLD, duplicated so
// that our messages never meet a host program's). Include it only in code built with an MPI
// library (CMake: EPONA_MPI, which links MPI::MPI_CXX). MPI errors come back as epona::Error
// naming the call, not as MPI's default abort.
#pragma once

#include <mpi.h>

#include <climits>
#include <cstdint>
#include <string>
#include <vector>

#include "epona/core/error.hpp"
#include "epona/dist/process_group.hpp"

namespace epona::dist {

class MpiProcessGroup final : public ProcessGroup {
 public:
  // Starts MPI unless the host program did (then it also stays the one to finalise it). MPI can
  // start once per process: after MPI_Finalize a second group is refused.
  MpiProcessGroup() {
    int started = 0, finished = 0;
    MPI_Initialized(&started);
    MPI_Finalized(&finished);
    EPONA_CHECK(!finished, "MPI has been finalised in this process already and cannot start again");
    if (!started) {
      int provided = 0;
      check(MPI_Init_thread(nullptr, nullptr, MPI_THREAD_FUNNELED, &provided), "MPI_Init_thread");
      owns_mpi_ = true;
    }
    check(MPI_Comm_dup(MPI_COMM_WORLD, &comm_), "MPI_Comm_dup");
    check(MPI_Comm_set_errhandler(comm_, MPI_ERRORS_RETURN), "MPI_Comm_set_errhandler");
    check(MPI_Comm_rank(comm_, &rank_), "MPI_Comm_rank");
    check(MPI_Comm_size(comm_, &size_), "MPI_Comm_size");
  }
  MpiProcessGroup(const MpiProcessGroup&) = delete;
  MpiProcessGroup& operator=(const MpiProcessGroup&) = delete;
  ~MpiProcessGroup() override {
    if (comm_ != MPI_COMM_NULL) MPI_Comm_free(&comm_);
    if (owns_mpi_) MPI_Finalize();
  }

  int rank() const override { return rank_; }
  int size() const override { return size_; }

  std::vector<std::string> gather_to_root(const std::string& bytes) override {
    const int mine = message_size(bytes.size());
    std::vector<int> counts(is_root() ? std::size_t(size_) : 0), offsets(counts.size());
    check(MPI_Gather(&mine, 1, MPI_INT, counts.data(), 1, MPI_INT, 0, comm_), "MPI_Gather");
    std::int64_t total = 0;
    for (std::size_t r = 0; r < counts.size(); ++r) offsets[r] = static_cast<int>(total), total += counts[r];
    EPONA_CHECK(total <= INT_MAX, "the ranks' results together (", total, " bytes) exceed one MPI message");
    std::string all(static_cast<std::size_t>(total), '\0');
    check(MPI_Gatherv(bytes.data(), mine, MPI_BYTE, all.data(), counts.data(), offsets.data(), MPI_BYTE, 0, comm_),
          "MPI_Gatherv");
    std::vector<std::string> out;
    for (std::size_t r = 0; r < counts.size(); ++r) out.push_back(all.substr(std::size_t(offsets[r]), std::size_t(counts[r])));
    return out;
  }

  std::string broadcast_from_root(const std::string& bytes) override {
    int n = is_root() ? message_size(bytes.size()) : 0;
    check(MPI_Bcast(&n, 1, MPI_INT, 0, comm_), "MPI_Bcast");
    std::string out = is_root() ? bytes : std::string(static_cast<std::size_t>(n), '\0');
    check(MPI_Bcast(out.data(), n, MPI_BYTE, 0, comm_), "MPI_Bcast");
    return out;
  }

 private:
  static int message_size(std::size_t bytes) {
    EPONA_CHECK(bytes <= std::size_t(INT_MAX), "a message of ", bytes, " bytes exceeds one MPI message");
    return static_cast<int>(bytes);
  }
  static void check(int code, const char* call) {
    if (code == MPI_SUCCESS) return;
    char text[MPI_MAX_ERROR_STRING] = {};
    int length = 0;
    MPI_Error_string(code, text, &length);
    fail(call, " failed: ", std::string(text, static_cast<std::size_t>(length)));
  }

  MPI_Comm comm_ = MPI_COMM_NULL;
  int rank_ = 0, size_ = 1;
  bool owns_mpi_ = false;
};

}  // namespace epona::dist
