// epona/cpu/gemm_driver.hpp — cache blocking and threading around the micro-kernels of
// gemm_kernels.hpp: C[M×N] = A[M×K]·B[K×N] with both operands packed into panels, K in blocks
// that keep an A micro-panel in L1 and a B block in L2, the output split into tasks among the
// OpenMP threads, and an epilogue run on each finished tile while it is in L1.
#pragma once

#include <algorithm>
#include <cstdint>
#include <memory>
#include <new>

#if defined(_OPENMP)
#include <omp.h>
#endif

#include "epona/cpu/gemm_kernels.hpp"

namespace epona::cpu::gemm {

// A grow-only 64-byte aligned word buffer, one per thread (OpenMP keeps its threads, so the
// buffers live across calls: no page faults per GEMM).
class WordBuffer {
 public:
  Word* get(std::int64_t n) {
    if (n > size_) {
      p_.reset(static_cast<Word*>(::operator new[](static_cast<std::size_t>(n) * sizeof(Word), std::align_val_t(64))));
      size_ = n;
    }
    return p_.get();
  }

 private:
  struct Free {
    void operator()(Word* p) const { ::operator delete[](p, std::align_val_t(64)); }
  };
  std::unique_ptr<Word[], Free> p_;
  std::int64_t size_ = 0;
};

inline WordBuffer& thread_buffer(int which) {
  thread_local WordBuffer buffers[3];  // 0: packed A (caller), 1: shared B (caller), 2: a task's B block
  return buffers[which];
}

// How a product is cut: K blocks of `kc` steps; the output in a grid of m_tasks × n_tasks
// tasks of whole panels; B packed once for all tasks (shared) when several tasks need the same
// columns, else by each task for its own columns (the weights are then read from memory once).
struct GemmPlan {
  std::int64_t M = 0, N = 0, S = 0;  // rows, columns, steps (k or pairs of k)
  std::int64_t mr = 0, nr = 0;
  std::int64_t kc = 0, k_blocks = 0;
  std::int64_t m_panels = 0, n_panels = 0;
  std::int64_t nc_panels = 0;                    // B panels per block
  std::int64_t m_tasks = 1, n_tasks = 1;
  std::int64_t m_per_task = 0, n_per_task = 0;   // panels
  bool shared_b = false;
  int threads = 1;

  std::int64_t tasks() const { return m_tasks * n_tasks; }
  std::int64_t block_steps(std::int64_t kb) const { return std::min(kc, S - kb * kc); }
  // Offset of panel p (of `padded` rows or columns in all) in K block kb of a packed operand.
  std::int64_t offset(std::int64_t kb, std::int64_t p, std::int64_t panel, std::int64_t padded) const {
    return kb * kc * padded + p * panel * block_steps(kb);
  }
};

// Each thread gets at least this many multiply-adds (~10 µs of one core's work): a parallel
// region and its barriers cost a few µs, so small products (TrajDiT's 15-token stream) use
// fewer threads than the context has.
inline constexpr double kMacsPerThread = 1 << 20;

inline GemmPlan plan_gemm(const KernelFamily& f, std::int64_t M, std::int64_t N, std::int64_t S, int threads) {
  GemmPlan p;
  p.M = M, p.N = N, p.S = S, p.mr = f.mr, p.nr = f.nr;
  p.k_blocks = std::max<std::int64_t>(1, (S + f.kc - 1) / f.kc);
  p.kc = ((S + p.k_blocks - 1) / p.k_blocks + f.k_align - 1) / f.k_align * f.k_align;  // even, aligned blocks
  p.m_panels = (M + f.mr - 1) / f.mr;
  p.n_panels = (N + f.nr - 1) / f.nr;
  p.nc_panels = std::max<std::int64_t>(1, f.nc / f.nr);
  const double macs = double(M) * double(N) * double(S) * f.k_per_step;
  const std::int64_t T = std::clamp<std::int64_t>(static_cast<std::int64_t>(macs / kMacsPerThread), 1, std::max(1, threads));
  // Columns first: each task then packs its own B block and reads the weights once. Narrow
  // the tasks (down to one panel) until every thread has one.
  p.n_per_task = std::min(p.n_panels, p.nc_panels);
  if ((p.n_panels + p.n_per_task - 1) / p.n_per_task < T) p.n_per_task = std::max<std::int64_t>(1, (p.n_panels + T - 1) / T);
  p.n_tasks = (p.n_panels + p.n_per_task - 1) / p.n_per_task;
  // Too few columns for the threads: split the rows as well, and pack B once for all tasks.
  if (p.n_tasks < T) {
    p.m_tasks = std::min(p.m_panels, (T + p.n_tasks - 1) / p.n_tasks);
    p.shared_b = p.m_tasks > 1;
  }
  p.m_per_task = (p.m_panels + p.m_tasks - 1) / p.m_tasks;
  p.m_tasks = (p.m_panels + p.m_per_task - 1) / p.m_per_task;
  p.threads = static_cast<int>(std::min<std::int64_t>(T, p.tasks()));
  return p;
}

// One task: rows [pm0, pm1) × columns [pn0, pn1) of panels, every K block.
template <class PackB, class Epilogue>
void run_task(const KernelFamily& f, const GemmPlan& p, std::int64_t pm0, std::int64_t pm1, std::int64_t pn0,
              std::int64_t pn1, const Word* packed_a, const Word* shared_b, PackB& pack_b, float* c,
              std::int64_t ldc, Epilogue& epilogue) {
  const std::int64_t mpad = p.m_panels * p.mr, npad = p.n_panels * p.nr;
  Word* block = p.shared_b ? nullptr : thread_buffer(2).get(p.nc_panels * p.nr * p.kc);
  for (std::int64_t j0 = pn0; j0 < pn1; j0 += p.nc_panels) {
    const std::int64_t j1 = std::min(pn1, j0 + p.nc_panels);
    for (std::int64_t kb = 0; kb < p.k_blocks; ++kb) {
      const std::int64_t steps = p.block_steps(kb), s0 = kb * p.kc;
      const bool last = kb + 1 == p.k_blocks;
      if (!p.shared_b) pack_b(j0 * p.nr, std::min(j1 * p.nr, p.N) - j0 * p.nr, s0, steps, block);
      for (std::int64_t i = pm0; i < pm1; ++i) {
        const std::int64_t m0 = i * p.mr, rows = std::min(p.mr, p.M - m0);
        const MicroKernel kernel = f.for_rows(rows);
        const Word* a = packed_a + p.offset(kb, i, p.mr, mpad);
        for (std::int64_t j = j0; j < j1; ++j) {
          const std::int64_t n0 = j * p.nr, cols = std::min(p.nr, p.N - n0);
          const Word* b = p.shared_b ? shared_b + p.offset(kb, j, p.nr, npad) : block + (j - j0) * p.nr * steps;
          kernel(a, b, steps, c + m0 * ldc + n0, ldc, cols, kb > 0);
          if (last) epilogue(m0, rows, n0, cols);
        }
      }
    }
  }
}

// C[M×N] (ldc) = A·B over S steps with the family's micro-kernels, then epilogue(m0, rows, n0,
// cols) on each finished tile. pack_a(m0, rows, s0, steps, dst) packs one A panel (rows ≤ MR),
// pack_b(n0, cols, s0, steps, dst) the B panels covering columns [n0, n0 + cols), panel j at
// dst + j·NR·steps, zero-padded (cols may span several panels: a packer may then walk the
// source in its own order); both are called from several threads at once.
template <class PackA, class PackB, class Epilogue>
void run_gemm(const KernelFamily& f, std::int64_t M, std::int64_t N, std::int64_t S, int threads, PackA&& pack_a,
              PackB&& pack_b, float* c, std::int64_t ldc, Epilogue&& epilogue) {
  if (M <= 0 || N <= 0) return;
  const GemmPlan p = plan_gemm(f, M, N, S, threads);
  const std::int64_t mpad = p.m_panels * p.mr, npad = p.n_panels * p.nr;
  Word* packed_a = thread_buffer(0).get(mpad * std::max<std::int64_t>(S, 1));
  Word* shared_b = p.shared_b ? thread_buffer(1).get(npad * std::max<std::int64_t>(S, 1)) : nullptr;
  const std::int64_t a_jobs = p.m_panels * p.k_blocks, b_jobs = p.shared_b ? p.n_panels * p.k_blocks : 0;
#pragma omp parallel num_threads(p.threads) if (p.threads > 1)
  {
#pragma omp for schedule(static) nowait
    for (std::int64_t job = 0; job < a_jobs + b_jobs; ++job) {
      if (job < a_jobs) {
        const std::int64_t kb = job / p.m_panels, i = job % p.m_panels;
        pack_a(i * p.mr, std::min(p.mr, M - i * p.mr), kb * p.kc, p.block_steps(kb),
               packed_a + p.offset(kb, i, p.mr, mpad));
      } else {
        const std::int64_t kb = (job - a_jobs) / p.n_panels, j = (job - a_jobs) % p.n_panels;
        pack_b(j * p.nr, std::min(p.nr, N - j * p.nr), kb * p.kc, p.block_steps(kb),
               shared_b + p.offset(kb, j, p.nr, npad));
      }
    }
#pragma omp barrier
#pragma omp for schedule(dynamic)
    for (std::int64_t t = 0; t < p.tasks(); ++t) {
      const std::int64_t tm = t % p.m_tasks, tn = t / p.m_tasks;
      const std::int64_t pm0 = tm * p.m_per_task, pm1 = std::min(p.m_panels, pm0 + p.m_per_task);
      const std::int64_t pn0 = tn * p.n_per_task, pn1 = std::min(p.n_panels, pn0 + p.n_per_task);
      run_task(f, p, pm0, pm1, pn0, pn1, packed_a, shared_b, pack_b, c, ldc, epilogue);
    }
  }
}

}  // namespace epona::cpu::gemm
