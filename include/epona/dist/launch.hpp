// epona/dist/launch.hpp — where this process stands in a job of several: its rank, the job's size
// and its rank among the processes of its host, as the launcher that started it says in the
// environment (OpenMPI's mpirun, an MPICH/Hydra-style PMI launcher, or a Slurm job step's srun).
// Reading it needs no MPI library, so a program can refuse a multi-process launch it cannot
// serve, or pick its GPU, before any runtime starts.
#pragma once

#include <cerrno>
#include <cstdlib>
#include <string>

#include "epona/core/error.hpp"

namespace epona::dist {

struct Launch {
  int rank = 0, size = 1;              // in the whole job
  int local_rank = 0, local_size = 1;  // among the job's processes on this host (Slurm: size unknown, the job's)
  std::string launcher = "none";       // which variables said so: "openmpi", "pmi", "slurm" or "none"
  bool several() const { return size > 1; }
};

namespace launch_detail {

// The integer value of `name`, or -1 when unset (or no name); an epona::Error when set to something else.
inline int env_int(const char* name) {
  const char* v = name ? std::getenv(name) : nullptr;
  if (!v || !*v) return -1;
  errno = 0;
  char* end = nullptr;
  const long n = std::strtol(v, &end, 10);
  EPONA_CHECK(errno == 0 && *end == '\0' && n >= 0 && n < (1L << 24), "the launcher's variable ", name,
              " is not a process count or index: '", v, "'");
  return static_cast<int>(n);
}

// Rank and size from one launcher's variables; false when its size variable is unset.
inline bool read_launch(Launch& l, const char* launcher, const char* rank, const char* size, const char* local_rank,
                        const char* local_size) {
  const int n = env_int(size);
  if (n < 0) return false;
  const int r = env_int(rank), lr = env_int(local_rank), ln = env_int(local_size);
  EPONA_CHECK(n >= 1 && r >= 0 && r < n, "the launcher's ", rank, " (", r, ") is not a rank of ", size, " = ", n);
  l = Launch{r, n, lr >= 0 ? lr : r, ln >= 1 ? ln : n, launcher};
  EPONA_CHECK(l.local_rank < l.local_size, "the launcher's ", local_rank, " (", l.local_rank, ") is not below ",
              local_size, " (", l.local_size, ")");
  return true;
}

}  // namespace launch_detail

// The launch this process belongs to; a lone process (no launcher) is rank 0 of 1. Slurm is read
// only inside a job step (SLURM_STEP_NUM_TASKS): a batch script's own shell is one process even
// when the allocation has several tasks.
inline Launch launch_from_environment() {
  using launch_detail::read_launch;
  Launch l;
  if (read_launch(l, "openmpi", "OMPI_COMM_WORLD_RANK", "OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_LOCAL_RANK",
                  "OMPI_COMM_WORLD_LOCAL_SIZE"))
    return l;
  if (read_launch(l, "pmi", "PMI_RANK", "PMI_SIZE", "MPI_LOCALRANKID", "MPI_LOCALNRANKS")) return l;
  if (read_launch(l, "slurm", "SLURM_PROCID", "SLURM_STEP_NUM_TASKS", "SLURM_LOCALID", nullptr))
    return l;
  return l;
}

// The items of 0..count-1 that `rank` of `size` takes: every size-th from its rank, so that the
// ranks' shares differ by at most one item and neighbouring items (often alike in cost) spread.
template <class F>
void for_each_share(std::size_t count, int rank, int size, F&& f) {
  for (std::size_t i = static_cast<std::size_t>(rank); i < count; i += static_cast<std::size_t>(size)) f(i);
}

// How many items for_each_share gives `rank`.
inline std::size_t share_size(std::size_t count, int rank, int size) {
  return (count + static_cast<std::size_t>(size - 1 - rank)) / static_cast<std::size_t>(size);
}

}  // namespace epona::dist
