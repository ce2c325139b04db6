// apps/epona/engine.hpp — the engine a command runs (model_engine.hpp): make_engine picks the
// backend and weight type the user chose, and with --tensor-parallel N the engine whose VisDiT is
// split over N shards (sharded_engine.hpp).
#pragma once

#include <memory>

#include "epona/cpu/thread_shard_sum.hpp"
#include "model_engine.hpp"
#include "models.hpp"
#include "sharded_engine.hpp"

namespace epona::app {

#if defined(EPONA_APP_CUDA)
// Defined in apps/epona/cuda_engine.cu (nvcc): ModelEngine<Cuda, float or bf16>.
std::unique_ptr<Engine> make_cuda_engine(const ComputeOptions& c);
#endif

// The CPU engine of weight type W: whole, or split over c.shards threads.
template <class W>
std::unique_ptr<Engine> make_cpu_engine(const ComputeOptions& c) {
  if (c.shards == 1) return std::make_unique<ModelEngine<Cpu, W>>(c);
  return std::make_unique<ShardedEngine<Cpu, W, cpu::ThreadShardGroup>>(
      c, std::make_unique<cpu::ThreadShardGroup>(c.shards), "");
}

// The engine for --backend/--dtype/--tensor-parallel (check_backend has refused what this
// program cannot run). Defined in apps/epona/cli.cpp: a unit that only calls it (the GPU test of
// the engines) then does not compile the CPU model again.
std::unique_ptr<Engine> make_engine(const ComputeOptions& c);

}  // namespace epona::app
