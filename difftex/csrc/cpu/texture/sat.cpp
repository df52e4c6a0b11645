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
// weights times the output gradient) is sparse, and the adjoint of the
// prefix sums is a suffix sum: grad f[r, c] = sum_{b > r, a > c} gS[b, a].
// Its entries are sorted by table row and swept bottom up (sat_backward),
// threaded over row blocks that start from the totals of the blocks below
// them. The gradients of the positions and coefficients are per point: the
// forward returns their Jacobians ([C, M, K]) when asked, so the backward
// never rebuilds the table.
#include "boxes.h"
#include "common.h"

#include "stable.h"

#include <memory>
#include <mutex>

namespace difftex {
namespace {

// A float64 buffer kept between calls (slot 0: the forward's table; one more slot spare): a fresh
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

void check_terms(const Tensor& texture, const Tensor& pu, const Tensor& cu,
                 const Tensor& pv, const Tensor& cv) {
  DT_CHECK(texture.dim() == 3 && texture.is_contiguous() && texture.is_cpu() &&
                  (texture.scalar_type() == kFloat32 || texture.scalar_type() == kFloat64),
              "sat: texture must be a contiguous CPU [C, H, W] float32 / float64 tensor");
  for (const auto* t : {&pu, &cu, &pv, &cv})
    DT_CHECK(t->dim() == 2 && t->is_contiguous() && t->scalar_type() == kFloat64 && t->is_cpu(),
                "sat: positions and coefficients must be contiguous CPU float64 [M, K]");
  DT_CHECK(cu.sizes() == pu.sizes() && cv.sizes() == pv.sizes() && pu.size(0) == pv.size(0),
              "sat: pu, cu must be [M, Ku] and pv, cv [M, Kv]");
  DT_CHECK(pu.size(1) <= 4 && pv.size(1) <= 4, "sat: at most 4 terms per axis");
}

// The table [H + 1][W + 1][C] of texture [C, H, W] (float64).
template <typename scalar_t>
void build_table(const scalar_t* f, int64_t C, int64_t H, int64_t W, double* S) {
  const int64_t row = (W + 1) * C;
  std::fill(S, S + row, 0.0);
  const int64_t T = std::max<int64_t>(1, std::min<int64_t>(get_num_threads(), H / 64));
  // Each block's rows with the rows above the block taken as zero.
  parallel_for(0, T, 1, [&](int64_t t0, int64_t t1) {
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
    parallel_for(1, T, 1, [&](int64_t t0, int64_t t1) {
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

std::vector<Tensor> sat_forward(Tensor texture, Tensor pu, Tensor cu, Tensor pv,
                                       Tensor cv, bool jacobians, bool coef_grads) {
  check_terms(texture, pu, cu, pv, cv);
  const int64_t C = texture.size(0), H = texture.size(1), W = texture.size(2);
  const int64_t M = pu.size(0), Ku = pu.size(1), Kv = pv.size(1), row = (W + 1) * C;
  auto opts = options_of(pu);
  auto out = empty({C, M}, opts);
  Tensor jpu, jcu, jpv, jcv;
  if (jacobians) {
    jpu = empty({C, M, Ku}, opts);
    jcu = empty({C, M, Ku}, opts);
    jpv = empty({C, M, Kv}, opts);
    jcv = empty({C, M, Kv}, opts);
  }
  Scratch S(0, static_cast<size_t>((H + 1) * row));
  DT_DISPATCH_FLOATING_TYPES(texture.scalar_type(), "sat_forward", [&] {
    build_table(texture.mutable_data_ptr<scalar_t>(), C, H, W, S.data());
  });
  const double *ppu = pu.mutable_data_ptr<double>(), *pcu = cu.mutable_data_ptr<double>(), *ppv = pv.mutable_data_ptr<double>(),
               *pcv = cv.mutable_data_ptr<double>();
  double* po = out.mutable_data_ptr<double>();
  double* J[4] = {jacobians ? jpu.mutable_data_ptr<double>() : nullptr, jacobians ? jcu.mutable_data_ptr<double>() : nullptr,
                  jacobians ? jpv.mutable_data_ptr<double>() : nullptr, jacobians ? jcv.mutable_data_ptr<double>() : nullptr};
  const double* tab = S.data();
  parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
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
          // A term with a zero coefficient adds nothing but its coefficient's gradient (e.g. the whole periods
          // of a repeat box that does not wrap): skipped where that is not asked for.
          if (!coef_grads && cvl[l] == 0) continue;
          const double* r0 = tab + y[l].i * row + c;
          const double* r1 = r0 + row;
          const double sy = y[l].s;
          for (int64_t k = 0; k < Ku; ++k) {
            if (!coef_grads && cuk[k] == 0) continue;
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
              if (coef_grads) {
                dcu[k] += cvl[l] * val;
                dcv[l] += cuk[k] * val;
              }
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

namespace {

// One scattered read of the table's gradient: row b of the table, columns a and a + 1 with weights w0, w1 (times
// point e's output gradient).
struct Entry {
  int64_t e, a;
  double w0, w1;
};

}  // namespace

Tensor sat_backward(Tensor texture, Tensor pu, Tensor cu, Tensor pv,
                           Tensor cv, Tensor grad) {
  check_terms(texture, pu, cu, pv, cv);
  const int64_t C = texture.size(0), H = texture.size(1), W = texture.size(2);
  const int64_t M = pu.size(0), Ku = pu.size(1), Kv = pv.size(1);
  // Any strides (a transposed output gradient is read in place).
  DT_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == kFloat64,
              "sat: grad must be float64 [C, M]");
  const int64_t gsc = grad.stride(0), gsm = grad.stride(1);
  auto out = empty({C, H, W}, options_of(texture));
  const double *ppu = pu.mutable_data_ptr<double>(), *pcu = cu.mutable_data_ptr<double>(), *ppv = pv.mutable_data_ptr<double>(),
               *pcv = cv.mutable_data_ptr<double>(), *pg = grad.mutable_data_ptr<double>();
  // The table's gradient is sparse (two rows of two entries per read): its entries are sorted by table row
  // (a counting sort), and the suffix sums sweep the rows bottom up with one dense row of the table's gradient
  // and the running column sums (each W x C doubles, in cache) instead of a texture-sized float64 buffer: the
  // texture's gradient is written once and nothing else texture-sized is touched (measured: 2-3x faster than
  // zero-filling, scattering into and sweeping a float64 table). Table row 0 is constant (no texel gets its
  // gradient).
  std::vector<int64_t> start(H + 2, 0);
  auto for_entries = [&](auto&& emit) {
    for (int64_t e = 0; e < M; ++e)
      for (int64_t l = 0; l < Kv; ++l) {
        const double cvl = pcv[e * Kv + l];
        if (cvl == 0) continue;  // a term with a zero coefficient scatters nothing
        const Cell y = cell(ppv[e * Kv + l], H);
        for (int64_t k = 0; k < Ku; ++k) {
          if (pcu[e * Ku + k] == 0) continue;
          const Cell x = cell(ppu[e * Ku + k], W);
          const double w = pcu[e * Ku + k] * cvl;
          emit(y.i, Entry{e, x.i, w * (1 - x.s) * (1 - y.s), w * x.s * (1 - y.s)});
          emit(y.i + 1, Entry{e, x.i, w * (1 - x.s) * y.s, w * x.s * y.s});
        }
      }
  };
  for_entries([&](int64_t b, const Entry&) { ++start[b + 1]; });
  for (int64_t b = 0; b <= H; ++b) start[b + 1] += start[b];
  std::unique_ptr<Entry[]> entries(new Entry[static_cast<size_t>(start[H + 1])]);
  {
    std::vector<int64_t> fill(start.begin(), start.end() - 1);
    for_entries([&](int64_t b, const Entry& x) { entries[fill[b]++] = x; });
  }
  // Row blocks per thread: table rows [b0, b1) with b0 = 1 + H t / T (texture rows one lower).
  const int64_t T = std::max<int64_t>(1, std::min<int64_t>(get_num_threads(), H / 64));
  const int64_t WC = W * C, RC = (W + 1) * C;
  // offset[t]: the column suffix sums of every table row below block t (from the blocks' own totals).
  std::vector<double> offset(static_cast<size_t>(T * WC), 0.0);
  auto add_row = [&](int64_t b, double* R) {  // R[(a) C + c] += the table-gradient row b
    for (int64_t n = start[b]; n < start[b + 1]; ++n) {
      const Entry& x = entries[n];
      double* r = R + x.a * C;
      for (int64_t c = 0; c < C; ++c) {
        const double g = pg[c * gsc + x.e * gsm];
        r[c] += g * x.w0;
        r[C + c] += g * x.w1;
      }
    }
  };
  auto suffix_into = [&](const double* R, double* acc, std::vector<double>& run) {  // acc += suffix sums of R
    std::fill(run.begin(), run.end(), 0.0);
    for (int64_t a = W - 1; a >= 0; --a)
      for (int64_t c = 0; c < C; ++c) {
        run[c] += R[(a + 1) * C + c];
        acc[a * C + c] += run[c];
      }
  };
  if (T > 1) {
    // Each block's total (the sum of its rows, suffix-summed once), then the totals below each block.
    std::vector<double> total(static_cast<size_t>(T * WC), 0.0);
    parallel_for(0, T, 1, [&](int64_t t0, int64_t t1) {
      std::vector<double> R(RC), run(C);
      for (int64_t t = t0; t < t1; ++t) {
        std::fill(R.begin(), R.end(), 0.0);
        for (int64_t b = 1 + block_start(t, T, H); b < 1 + block_start(t + 1, T, H); ++b) add_row(b, R.data());
        suffix_into(R.data(), total.data() + t * WC, run);
      }
    });
    for (int64_t t = T - 2; t >= 0; --t)
      for (int64_t x = 0; x < WC; ++x) offset[t * WC + x] = offset[(t + 1) * WC + x] + total[(t + 1) * WC + x];
  }
  DT_DISPATCH_FLOATING_TYPES(texture.scalar_type(), "sat_backward", [&] {
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    parallel_for(0, T, 1, [&](int64_t t0, int64_t t1) {
      std::vector<double> R(RC), acc(WC), run(C);
      for (int64_t t = t0; t < t1; ++t) {
        std::copy(offset.data() + t * WC, offset.data() + (t + 1) * WC, acc.begin());
        for (int64_t b = block_start(t + 1, T, H); b >= 1 + block_start(t, T, H); --b) {
          std::fill(R.begin(), R.end(), 0.0);
          add_row(b, R.data());
          suffix_into(R.data(), acc.data(), run);
          for (int64_t c = 0; c < C; ++c) {
            scalar_t* o = po + (c * H + b - 1) * W;
            for (int64_t a = 0; a < W; ++a) o[a] = static_cast<scalar_t>(acc[a * C + c]);
          }
        }
      }
    });
  });
  return out;
}

}  // namespace difftex
