// epona/dist/process_group.hpp — the few collective operations a job of several processes needs to
// split work over its ranks and bring the results together (data parallelism: every rank runs the
// whole model on its share of the items). An interface, so that code written against it runs the
// same as one process (LoneProcess) or under MPI (dist/mpi_process_group.hpp, which alone needs
// <mpi.h>). Bytes in, bytes out: what the bytes mean is the caller's.
#pragma once

#include <string>
#include <vector>

namespace epona::dist {

class ProcessGroup {
 public:
  virtual ~ProcessGroup() = default;
  virtual int rank() const = 0;
  virtual int size() const = 0;
  bool is_root() const { return rank() == 0; }
  // Every rank's bytes in rank order on rank 0; an empty list on the other ranks. Collective:
  // every rank calls it.
  virtual std::vector<std::string> gather_to_root(const std::string& bytes) = 0;
  // Rank 0's bytes on every rank (the others' argument is ignored). Collective.
  virtual std::string broadcast_from_root(const std::string& bytes) = 0;
};

// A job of one: the collectives are the identity.
class LoneProcess final : public ProcessGroup {
 public:
  int rank() const override { return 0; }
  int size() const override { return 1; }
  std::vector<std::string> gather_to_root(const std::string& bytes) override { return {bytes}; }
  std::string broadcast_from_root(const std::string& bytes) override { return bytes; }
};

}  // namespace epona::dist
