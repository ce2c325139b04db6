// apps/epona/processes.hpp — `eval` and `generate` across several processes (data parallelism):
// launched by mpirun or srun, each rank takes every size-th clip, runs the whole model on it, and
// rank 0 gathers the results (include/epona/dist/). Without a launcher the same code runs as one
// process. Each rank on a GPU host gets its own GPU (its local rank among the visible ones).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "console.hpp"
#include "models.hpp"
#include "epona/core/error.hpp"
#include "epona/dist/launch.hpp"
#include "epona/dist/message.hpp"
#include "epona/dist/process_group.hpp"
#if defined(EPONA_APP_MPI)
#include "epona/dist/mpi_process_group.hpp"
#endif

namespace epona::app {

// The commands that split their clips over the processes of a job; the others refuse a launch of
// several (every rank would write the same outputs).
inline bool splits_over_processes(const std::string& command) { return command == "eval" || command == "generate"; }

inline void check_launch(const dist::Launch& l, const std::string& command) {
  if (!l.several()) return;
  EPONA_CHECK(splits_over_processes(command), command, " runs as one process, but ", l.launcher, " started ", l.size,
              " (this is rank ", l.rank, "): run it alone, or use eval or generate --clips, which split their clips "
              "over the processes");
}

// The group this process belongs to: alone, or the MPI job its launcher started.
inline std::unique_ptr<dist::ProcessGroup> join_job(const dist::Launch& l) {
  if (!l.several()) return std::make_unique<dist::LoneProcess>();
#if defined(EPONA_APP_MPI)
  auto group = std::make_unique<dist::MpiProcessGroup>();
  EPONA_CHECK(group->size() == l.size && group->rank() == l.rank, "MPI says rank ", group->rank(), " of ",
              group->size(), " but ", l.launcher, "'s variables say rank ", l.rank, " of ", l.size);
  return group;
#else
  fail(l.launcher, " started ", l.size, " processes (this is rank ", l.rank, "), but this epona was built without MPI: "
       "install libopenmpi-dev and configure with -DEPONA_MPI=ON, or run one process");
#endif
}

namespace processes_detail {

inline std::vector<std::string> split_list(const std::string& s) {
  std::vector<std::string> out;
  std::size_t start = 0;
  while (start <= s.size()) {
    const std::size_t end = std::min(s.find(',', start), s.size());
    if (end > start) out.push_back(s.substr(start, end - start));
    start = end + 1;
  }
  return out;
}

// The NVIDIA GPUs of this host as the driver lists them, without starting the CUDA runtime (which
// reads CUDA_VISIBLE_DEVICES once, when it starts).
inline std::size_t driver_gpu_count() {
  std::error_code ec;
  std::size_t n = 0;
  for (const auto& e : std::filesystem::directory_iterator("/proc/driver/nvidia/gpus", ec)) n += e.is_directory(ec);
  return n;
}

}  // namespace processes_detail

// One GPU per rank of a host: CUDA_VISIBLE_DEVICES narrowed to the local rank's entry of the
// visible GPUs (all of the driver's when unset), before anything starts the CUDA runtime. Left
// alone when one GPU is visible (the launcher gave each rank its own, as srun --gpus-per-task does).
inline void assign_gpu(const dist::Launch& l, const Console& con) {
  if (!l.several()) return;
  const char* visible = std::getenv("CUDA_VISIBLE_DEVICES");
  std::vector<std::string> ids;
  if (visible) {
    ids = processes_detail::split_list(visible);
  } else {
    for (std::size_t i = 0; i < processes_detail::driver_gpu_count(); ++i) ids.push_back(std::to_string(i));
  }
  if (ids.size() <= 1) return;
  const std::string& mine = ids[static_cast<std::size_t>(l.local_rank) % ids.size()];
  ::setenv("CUDA_VISIBLE_DEVICES", mine.c_str(), 1);
  if (l.local_rank == 0 && static_cast<std::size_t>(l.local_size) > ids.size())
    con.note("note: ", l.local_size, " processes on this host share ", ids.size(), " GPUs");
}

// Runs `work` on every rank and returns what each returned, in rank order, on rank 0 (an empty
// list on the others). A failure on any rank fails rank 0 naming that rank; a lone process
// rethrows its own error as it was. The other ranks return normally even when their work failed:
// rank 0 reports it and its exit status is the job's (a rank exiting with an error first would
// have the launcher kill rank 0 before it could say why).
inline std::vector<std::string> run_on_every_rank(dist::ProcessGroup& g, const std::function<std::string()>& work) {
  std::exception_ptr error;
  dist::MessageWriter outcome;
  try {
    outcome.put(std::uint8_t{1}).put(work());
  } catch (const std::exception& e) {
    error = std::current_exception();
    outcome = dist::MessageWriter();
    outcome.put(std::uint8_t{0}).put(std::string(e.what()));
  }
  if (g.size() == 1 && error) std::rethrow_exception(error);
  std::vector<std::string> by_rank;
  const std::vector<std::string> gathered = g.gather_to_root(outcome.bytes());
  for (std::size_t rank = 0; rank < gathered.size(); ++rank) {
    dist::MessageReader in(gathered[rank]);
    const bool ok = in.get<std::uint8_t>() != 0;
    std::string text = in.get_string();
    if (!ok) fail("process ", rank, " of ", g.size(), ": ", text);
    by_rank.push_back(std::move(text));
  }
  return by_rank;
}

// A process's place in its job: the launch, the group, and its console (rank 0 speaks; the others
// only fail, and rank 0 names their errors too).
struct Job {
  dist::Launch launch;
  std::unique_ptr<dist::ProcessGroup> group;
  Console con;
  bool several() const { return group->size() > 1; }
  // ", split over N processes (launcher)" for the notes; empty alone.
  std::string split_note() const {
    return several() ? ", split over " + std::to_string(group->size()) + " processes (" + launch.launcher + ")" : "";
  }
};

// Joins the job this process was launched in (alone without a launcher), and on a GPU host takes
// this rank's GPU before anything starts CUDA.
inline Job join_job(const Console& console, const ComputeOptions& compute) {
  const dist::Launch launch = dist::launch_from_environment();
  auto group = join_job(launch);
  EPONA_CHECK(group->size() == 1 || compute.shards == 1, "--tensor-parallel ", compute.shards, " under ",
              launch.launcher, "'s ", group->size(), " processes: each process would take ", compute.shards,
              " GPUs of its host; split the clips over processes or one model over GPUs, not both");
  const bool root = group->is_root();
  Job j{launch, std::move(group), root ? console : Console{console.out, console.err, true, false}};
  if (compute.backend == "cuda") assign_gpu(j.launch, j.con);
  return j;
}

// Starts item i of a share message (writes its index) and returns the writer for its contents.
using ItemWriter = std::function<dist::MessageWriter&(std::size_t)>;

// This rank's share of `count` items as one message for run_on_every_rank, worked in batches of up
// to `batch` consecutive items of the share: `work(indices, item)` calls item(i) for each index of
// the batch, in order, and writes that item's contents after it.
template <class Work>
std::string share_message_in_batches(const dist::ProcessGroup& g, std::size_t count, std::size_t batch, Work&& work) {
  EPONA_CHECK(batch >= 1, "internal: a batch of no items");
  std::vector<std::size_t> mine;
  dist::for_each_share(count, g.rank(), g.size(), [&](std::size_t i) { mine.push_back(i); });
  dist::MessageWriter m;
  m.put(static_cast<std::uint64_t>(mine.size()));
  const ItemWriter item = [&m](std::size_t i) -> dist::MessageWriter& { return m.put(static_cast<std::uint64_t>(i)); };
  for (std::size_t first = 0; first < mine.size(); first += batch) {
    const auto last = mine.begin() + static_cast<std::ptrdiff_t>(std::min(first + batch, mine.size()));
    work(std::vector<std::size_t>(mine.begin() + static_cast<std::ptrdiff_t>(first), last), item);
  }
  return m.bytes();
}

// Every rank's share_message_in_batches read back into item order by `get(message)`; each item exactly once.
template <class T, class Get>
std::vector<T> items_in_order(const std::vector<std::string>& by_rank, std::size_t count, Get&& get) {
  std::vector<std::optional<T>> slots(count);
  for (const auto& bytes : by_rank) {
    dist::MessageReader m(bytes);
    for (auto n = m.get<std::uint64_t>(); n > 0; --n) {
      const auto i = m.get<std::uint64_t>();
      EPONA_CHECK(i < count && !slots[i], "internal: item ", i, " came back twice or out of range");
      slots[i] = get(m);
    }
  }
  std::vector<T> out;
  for (std::size_t i = 0; i < count; ++i) {
    EPONA_CHECK(slots[i].has_value(), "internal: no process returned item ", i);
    out.push_back(std::move(*slots[i]));
  }
  return out;
}

}  // namespace epona::app
