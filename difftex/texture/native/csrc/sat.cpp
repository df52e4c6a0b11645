// The summed-area-table filter's box sums on the CPU (filters/sat.py
// _BoxSums; box_sums_reference is the tested reference), forward and
// first-order backward.
//
// A point's box sum is sum_k sum_l cu_k cv_l S~(pu_k, pv_l): S~ the bilinear
// interpolation of the table S[b, a] = sum_{r < b, c < a} f[r, c] ([H + 1,
// W + 1]), cell i = clamp(floor(p), 0, n - 1) and fraction p - i per axis
// (as box_sums_reference). Positions and coefficients come from Python (the
// wrap terms of sat.py _axis_terms, cheap [M, K] torch ops); the
// texture-sized work is here: the table, the reads and the adjoint.
//
// Table: float64 (sat.py's precision argument), interleaved [H + 1][W + 1][C]
// so that a read's channels are adjacent. Built in one pass per row block
// (each row: a running sum along the row plus the row above), threaded over
// row blocks with a fix-up that adds the rows above a block to it.
//
// Backward to the texture: the table's gradient (each read's bilinear
// weights times the output gradient) is scattered into a float64 buffer of
// the table's shape, and the adjoint of the prefix sums is a suffix sum:
// grad f[r, c] = sum_{b > r, a > c} gS[b, a]. Threads own row blocks of the
// buffer: each one walks every point and writes only the rows it owns (no
// lock, deterministic, the same result for any thread count), then suffix-
// sums its rows; a fix-up adds the rows below each block. The gradients of
// the positions and coefficients are per point: the forward returns their
// Jacobians ([C, M, K]) when asked, so the backward never rebuilds the table.
#include "boxes.h"
#include "common.h"

#include <ATen/Parallel.h>

#include <memory>
#include <mutex>

namespace difftex {
namespace {

// A float64 buffer kept between calls (slot 0: the forward's table, 1: the backward's gradient table): a fresh
// texture-sized allocation is fresh pages, and their faults cost about as much as one pass over them (the torch
// path spent a fifth of its time in page faults, perf). Buffers over kKeepBytes are not kept (a 4096^2 RGB
// table is 400 MB); a call that finds its slot busy (another thread in the kernel) allocates its own.
constexpr size_t kKeepBytes = size_t{160} << 20;

class Scratch {
 public:
  Scratch(int slot, size_t n) {
    static std::mutex mutex[2];
    static std::vector<double> kept[2];
    if (n * sizeof(double) <= kKeepBytes) {
      lock_ = std::unique_lock<std::mutex>(mutex[slot], std::try_to_lock);
      if (lock_.owns_lock()) {
        if (kept[slot].size() < n) kept[slot].resize(n);
        data_ = kept[slot].data();
        return;
      }
    }
    own_.reset(new double[n]);  // uninitialized: every entry used is written first
    data_ = own_.get();
  }
  double* data() { return data_; }

 private:
  std::unique_lock<std::mutex> lock_;
  std::unique_ptr<double[]> own_;
  double* data_ = nullptr;
};

// Row blocks for T threads over rows [0, n): block t is [n t / T, n (t + 1) / T).
inline int64_t block_start(int64_t t, int64_t T, int64_t n) { return n * t / T; }

// One axis of a table read: cell and fraction (box_sums_reference: i = clamp(floor(p), 0, n - 1), s = p - i,
// extrapolating linearly outside [0, n]; a NaN p gives a NaN fraction).
struct Cell {
  int64_t i;
  double s;
};

DT_INLINE Cell cell(double p, int64_t n) {
  double f = floor_capped(p);
  f = f < 0 ? 0 : (f > n - 1 ? static_cast<double>(n - 1) : f);
  return {static_cast<int64_t>(f), std::isnan(p) ? p : p - f};
}

void check_terms(const torch::Tensor& texture, const torch::Tensor& pu, const torch::Tensor& cu,
                 const torch::Tensor& pv, const torch::Tensor& cv) {
  TORCH_CHECK(texture.dim() == 3 && texture.is_contiguous() && texture.device().is_cpu() &&
                  (texture.scalar_type() == torch::kFloat || texture.scalar_type() == torch::kDouble),
              "sat: texture must be a contiguous CPU [C, H, W] float32 / float64 tensor");
  for (const auto* t : {&pu, &cu, &pv, &cv})
    TORCH_CHECK(t->dim() == 2 && t->is_contiguous() && t->scalar_type() == torch::kDouble && t->device().is_cpu(),
                "sat: positions and coefficients must be contiguous CPU float64 [M, K]");
  TORCH_CHECK(cu.sizes() == pu.sizes() && cv.sizes() == pv.sizes() && pu.size(0) == pv.size(0),
              "sat: pu, cu must be [M, Ku] and pv, cv [M, Kv]");
  TORCH_CHECK(pu.size(1) <= 4 && pv.size(1) <= 4, "sat: at most 4 terms per axis");
}

// The table [H + 1][W + 1][C] of texture [C, H, W] (float64).
template <typename scalar_t>
void build_table(const scalar_t* f, int64_t C, int64_t H, int64_t W, double* S) {
  const int64_t row = (W + 1) * C;
  std::fill(S, S + row, 0.0);
  const int64_t T = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), H / 64));
  // Each block's rows with the rows above the block taken as zero.
  at::parallel_for(0, T, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t r0 = block_start(t, T, H), r1 = block_start(t + 1, T, H);
      std::vector<double> run(C);
      std::vector<const scalar_t*> src(C);
      for (int64_t r = r0; r < r1; ++r) {
        double* out = S + (r + 1) * row;
        // The first row of a block starts from zero (the fix-up below adds the rows above); the others add the
        // row above, contiguous with this one's writes.
        const double* up = r > r0 ? out - row : nullptr;
        for (int64_t c = 0; c < C; ++c) {
          src[c] = f + (c * H + r) * W;
          run[c] = 0.0;
          out[c] = 0.0;
        }
        for (int64_t a = 0; a < W; ++a) {
          double* o = out + (a + 1) * C;
          for (int64_t c = 0; c < C; ++c) {
            run[c] += static_cast<double>(src[c][a]);
            o[c] = up ? run[c] + up[(a + 1) * C + c] : run[c];
          }
        }
      }
    }
  });
  if (T > 1) {
    // Block t's rows get the last row of block t - 1 (already complete when blocks go in order): a serial
    // chain of one row per block, then each block's other rows in parallel.
    for (int64_t t = 1; t < T; ++t) {
      const int64_t r1 = block_start(t + 1, T, H);
      const double* off = S + block_start(t, T, H) * row;  // the row above the block, complete
      double* last = S + r1 * row;
      for (int64_t x = 0; x < row; ++x) last[x] += off[x];
    }
    at::parallel_for(1, T, 1, [&](int64_t t0, int64_t t1) {
      for (int64_t t = t0; t < t1; ++t) {
        const int64_t r0 = block_start(t, T, H), r1 = block_start(t + 1, T, H);
        const double* off = S + r0 * row;
        for (int64_t r = r0 + 1; r < r1; ++r) {  // table rows r0 + 1 .. r1 - 1 (row r1 done above)
          double* out = S + r * row;
          for (int64_t x = 0; x < row; ++x) out[x] += off[x];
        }
      }
    });
  }
}

}  // namespace

std::vector<torch::Tensor> sat_forward(torch::Tensor texture, torch::Tensor pu, torch::Tensor cu, torch::Tensor pv,
                                       torch::Tensor cv, bool jacobians) {
  check_terms(texture, pu, cu, pv, cv);
  const int64_t C = texture.size(0), H = texture.size(1), W = texture.size(2);
  const int64_t M = pu.size(0), Ku = pu.size(1), Kv = pv.size(1), row = (W + 1) * C;
  auto opts = pu.options();
  auto out = torch::empty({C, M}, opts);
  torch::Tensor jpu, jcu, jpv, jcv;
  if (jacobians) {
    jpu = torch::empty({C, M, Ku}, opts);
    jcu = torch::empty({C, M, Ku}, opts);
    jpv = torch::empty({C, M, Kv}, opts);
    jcv = torch::empty({C, M, Kv}, opts);
  }
  Scratch S(0, static_cast<size_t>((H + 1) * row));
  AT_DISPATCH_FLOATING_TYPES(texture.scalar_type(), "sat_forward", [&] {
    build_table(texture.data_ptr<scalar_t>(), C, H, W, S.data());
  });
  const double *ppu = pu.data_ptr<double>(), *pcu = cu.data_ptr<double>(), *ppv = pv.data_ptr<double>(),
               *pcv = cv.data_ptr<double>();
  double* po = out.data_ptr<double>();
  double* J[4] = {jacobians ? jpu.data_ptr<double>() : nullptr, jacobians ? jcu.data_ptr<double>() : nullptr,
                  jacobians ? jpv.data_ptr<double>() : nullptr, jacobians ? jcv.data_ptr<double>() : nullptr};
  const double* tab = S.data();
  at::parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
    std::vector<double> buf(static_cast<size_t>(C) * 16 * 4);
    for (int64_t e = lo; e < hi; ++e) {
      Cell x[4], y[4];
      for (int64_t k = 0; k < Ku; ++k) x[k] = cell(ppu[e * Ku + k], W);
      for (int64_t l = 0; l < Kv; ++l) y[l] = cell(ppv[e * Kv + l], H);
      const double* cuk = pcu + e * Ku;
      const double* cvl = pcv + e * Kv;
      for (int64_t c = 0; c < C; ++c) {
        double total = 0.0;
        double dpu[4] = {0, 0, 0, 0}, dcu[4] = {0, 0, 0, 0}, dpv[4] = {0, 0, 0, 0}, dcv[4] = {0, 0, 0, 0};
        for (int64_t l = 0; l < Kv; ++l) {
          const double* r0 = tab + y[l].i * row + c;
          const double* r1 = r0 + row;
          const double sy = y[l].s;
          for (int64_t k = 0; k < Ku; ++k) {
            const int64_t a = x[k].i * C;
            const double sx = x[k].s;
            const double t00 = r0[a], t01 = r0[a + C], t10 = r1[a], t11 = r1[a + C];
            const double top = t00 + sx * (t01 - t00), bot = t10 + sx * (t11 - t10);
            const double val = top + sy * (bot - top);
            total += cuk[k] * cvl[l] * val;
            if (jacobians) {
              const double ddx = (1 - sy) * (t01 - t00) + sy * (t11 - t10);
              dpu[k] += cuk[k] * cvl[l] * ddx;
              dpv[l] += cuk[k] * cvl[l] * (bot - top);
              dcu[k] += cvl[l] * val;
              dcv[l] += cuk[k] * val;
            }
          }
        }
        po[c * M + e] = total;
        if (jacobians) {
          for (int64_t k = 0; k < Ku; ++k) {
            J[0][(c * M + e) * Ku + k] = dpu[k];
            J[1][(c * M + e) * Ku + k] = dcu[k];
          }
          for (int64_t l = 0; l < Kv; ++l) {
            J[2][(c * M + e) * Kv + l] = dpv[l];
            J[3][(c * M + e) * Kv + l] = dcv[l];
          }
        }
      }
    }
  });
  if (!jacobians) return {out};
  return {out, jpu, jcu, jpv, jcv};
}

torch::Tensor sat_backward(torch::Tensor texture, torch::Tensor pu, torch::Tensor cu, torch::Tensor pv,
                           torch::Tensor cv, torch::Tensor grad) {
  check_terms(texture, pu, cu, pv, cv);
  const int64_t C = texture.size(0), H = texture.size(1), W = texture.size(2);
  const int64_t M = pu.size(0), Ku = pu.size(1), Kv = pv.size(1), row = (W + 1) * C;
  // Any strides (a transposed output gradient is read in place).
  TORCH_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == torch::kDouble,
              "sat: grad must be float64 [C, M]");
  const int64_t gsc = grad.stride(0), gsm = grad.stride(1);
  auto out = torch::empty({C, H, W}, texture.options());
  const double *ppu = pu.data_ptr<double>(), *pcu = cu.data_ptr<double>(), *ppv = pv.data_ptr<double>(),
               *pcv = cv.data_ptr<double>(), *pg = grad.data_ptr<double>();
  // gS rows 1..H matter (row 0 of the table is constant, its gradient reaches no texel); block t owns table rows
  // [1 + H t / T, 1 + H (t + 1) / T), i.e. texture rows one lower.
  const int64_t T = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), H / 64));
  Scratch scratch(1, static_cast<size_t>((H + 1) * row));
  double* G = scratch.data();
  std::vector<double> totals(static_cast<size_t>(T * W * C), 0.0);  // each block's suffix sums over its rows
  AT_DISPATCH_FLOATING_TYPES(texture.scalar_type(), "sat_backward", [&] {
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, T, 1, [&](int64_t t0, int64_t t1) {
      for (int64_t t = t0; t < t1; ++t) {
        const int64_t b0 = 1 + block_start(t, T, H), b1 = 1 + block_start(t + 1, T, H);
        std::fill(G + b0 * row, G + b1 * row, 0.0);
        // The scatter of every point's reads into the rows owned.
        for (int64_t e = 0; e < M; ++e) {
          for (int64_t l = 0; l < Kv; ++l) {
            const Cell y = cell(ppv[e * Kv + l], H);
            if (y.i + 1 < b0 || y.i >= b1) continue;  // neither row y.i nor y.i + 1 owned
            const double cvl = pcv[e * Kv + l];
            for (int64_t k = 0; k < Ku; ++k) {
              const Cell x = cell(ppu[e * Ku + k], W);
              const double w = pcu[e * Ku + k] * cvl;
              const double wts[4] = {w * (1 - x.s) * (1 - y.s), w * x.s * (1 - y.s), w * (1 - x.s) * y.s,
                                     w * x.s * y.s};
              for (int q = 0; q < 2; ++q) {
                const int64_t b = y.i + q;
                if (b < b0 || b >= b1) continue;
                double* gr = G + b * row + x.i * C;
                for (int64_t c = 0; c < C; ++c) {
                  const double g = pg[c * gsc + e * gsm];
                  gr[c] += g * wts[2 * q];
                  gr[C + c] += g * wts[2 * q + 1];
                }
              }
            }
          }
        }
        // Suffix sums of the rows owned, bottom up: acc[a] = sum over the block's rows b' >= b of the row sums
        // past column a; texture row b - 1 gets acc (plus the blocks below, added after when T > 1).
        double* acc = totals.data() + t * W * C;
        std::vector<double> run(C);
        for (int64_t b = b1 - 1; b >= b0; --b) {
          const double* gr = G + b * row;
          std::fill(run.begin(), run.end(), 0.0);
          for (int64_t a = W - 1; a >= 0; --a) {
            for (int64_t c = 0; c < C; ++c) {
              run[c] += gr[(a + 1) * C + c];
              acc[a * C + c] += run[c];
            }
            if (T == 1)
              for (int64_t c = 0; c < C; ++c) po[(c * H + b - 1) * W + a] = static_cast<scalar_t>(acc[a * C + c]);
          }
          if (T > 1) std::copy(acc, acc + W * C, G + b * row);  // the block's partial, kept in double
        }
      }
    });
    if (T > 1) {
      // Block t's rows get the totals of every block below it.
      for (int64_t t = T - 2; t >= 0; --t) {
        double* below = totals.data() + (t + 1) * W * C;
        double* mine = totals.data() + t * W * C;
        for (int64_t x = 0; x < W * C; ++x) mine[x] += below[x];
      }
      // (totals[t] now holds blocks t .. T - 1; block t adds totals[t + 1].)
      at::parallel_for(0, T, 1, [&](int64_t t0, int64_t t1) {
        for (int64_t t = t0; t < t1; ++t) {
          const int64_t b0 = 1 + block_start(t, T, H), b1 = 1 + block_start(t + 1, T, H);
          const double* off = t + 1 < T ? totals.data() + (t + 1) * W * C : nullptr;
          for (int64_t b = b0; b < b1; ++b) {
            const double* gr = G + b * row;
            for (int64_t c = 0; c < C; ++c)
              for (int64_t a = 0; a < W; ++a)
                po[(c * H + b - 1) * W + a] = static_cast<scalar_t>(gr[a * C + c] + (off ? off[a * C + c] : 0.0));
          }
        }
      });
    }
  });
  return out;
}

}  // namespace difftex
