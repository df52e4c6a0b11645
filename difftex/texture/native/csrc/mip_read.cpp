// Trilinear / nearest-mip taps of a mip pyramid on the CPU, forward and
// first-order backward, one pass over the points (difftex/native.py): per
// point one tap (trilinear, nearest-mip) or N taps spread along an axis
// (anisotropic, auto), so no tap list is built.
//
// The semantics are those of difftex's torch path (filters/trilinear.py
// mip_blend + filters/basic.py bilinear + wrap.py), which stays the tested
// reference:
//   level k, texel coordinate x = u * w_k - 0.5 (texel j's centre at j),
//   taps floor(x) and floor(x) + 1, indices wrapped per axis as wrap.py
//   does (repeat: mod n; clamp: clamp; mirror: mod 2n reflected; border:
//   the constant outside); trilinear: k0 = floor(D), the lower level weighted
//   1 - (D - k0) and, where read, the upper one D - k0, so d/dD is
//   B(k0 + 1) - B(k0) (only -B(k0) where the upper level is not read).
//   The upper level is read where k0 < K - 1 and (D > k0, or D needs a
//   gradient and D > 0), as mip_blend does. A point with a non-finite uv
//   gives NaN and no gradient.
// Coordinates are computed in double, so float32 uv far from [0, 1] keep
// their sub-texel position; texel arithmetic is in the texture's dtype (as
// grid_sample's), with the channel count (1, 3, 4) and whether a border
// constant is read fixed at compile time (measured: 20-30% faster than
// double arithmetic with run-time checks, float32, 3 channels).
//
// Also here: the EWA filter, forward and first-order backward (ewa,
// ewa_backward); and, without gradients, the footprint front end of the
// bilinear-tap mip filters (front) and the pyramid's 2 x 2 box step (box2).
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

namespace {

// The per-tap helpers below are small and called in the innermost loops;
// left to itself the compiler keeps some out of line (measured: 20% of the
// forward in calls that return their structs through memory).
#if defined(_MSC_VER)
#define DT_INLINE __forceinline
#else
#define DT_INLINE inline __attribute__((always_inline))
#endif

enum Wrap { REPEAT = 0, CLAMP = 1, MIRROR = 2, BORDER = 3 };

// 2^52: from here on a double has no fractional part.
constexpr double kTwo52 = 4503599627370496.0;

// floor(x) without std::floor (a library call without SSE4.1): below 2^51
// rounded to nearest by adding and subtracting 1.5 * 2^52, then stepped
// down where that rounded up (no integer round trip: 10% off the backward);
// above, through an integer truncation. Capped at +-2^52, where no fraction
// is left anyway; NaN gives -2^52 (callers test finiteness).
DT_INLINE double floor_capped(double x) {
  if (std::abs(x) < 0.5 * kTwo52) {
    const double r = (x + 1.5 * kTwo52) - 1.5 * kTwo52;
    return r - (r > x ? 1.0 : 0.0);
  }
  if (!(x > -kTwo52)) return -kTwo52;
  if (!(x < kTwo52)) return kTwo52;
  double t = static_cast<double>(static_cast<int64_t>(x));
  return t > x ? t - 1.0 : t;
}

// x - floor(x) in [0, 1); 0 from 2^52 on, where doubles are integers.
DT_INLINE double frac(double x) {
  return std::abs(x) < kTwo52 ? x - floor_capped(x) : 0.0;
}

// One axis of a bilinear read: the two texels (and whether each is a texel
// rather than the border constant), the fraction, and d(folded u) / du.
// repeat and mirror fold u into one period first (as filters/fast.py does),
// so both taps land within one texel of the texture and no integer
// division is needed; the values are the integer wrap's.
struct Axis {
  int64_t i0, i1;
  bool in0, in1;
  double f, slope;
};

// repeat / mirror: u folded into one period, and d(folded u) / du; the same
// for every level, so computed once per tap.
struct Folded {
  double u, slope;
};

DT_INLINE Folded fold(double u, int mode) {
  if (mode == REPEAT) return {frac(u), 1.0};
  if (mode == MIRROR) {
    double f = frac(0.5 * u);
    return {1.0 - std::abs(2.0 * f - 1.0), f < 0.5 ? 1.0 : -1.0};
  }
  return {u, 1.0};
}

DT_INLINE Axis place(Folded fu, int64_t n, int mode) {
  Axis a;
  a.slope = fu.slope;
  a.in0 = a.in1 = true;
  double x = fu.u * static_cast<double>(n) - 0.5, x0 = floor_capped(x);
  a.f = std::abs(x) < kTwo52 ? x - x0 : 0.0;  // capped x0: no fraction left (clamp / border)
  int64_t i = static_cast<int64_t>(x0), j = i + 1;
  switch (mode) {
    case REPEAT:  // i in [-1, n - 1], j in [0, n]
      if (i < 0) i += n;
      if (j >= n) j -= n;
      break;
    case MIRROR:  // the edge texel is its own mirror image
      if (i < 0) i = 0;
      if (j >= n) j = n - 1;
      break;
    case CLAMP:
      i = i < 0 ? 0 : (i >= n ? n - 1 : i);
      j = j < 0 ? 0 : (j >= n ? n - 1 : j);
      break;
    default:
      a.in0 = i >= 0 && i < n;
      a.in1 = j >= 0 && j < n;
      if (!a.in0) i = 0;
      if (!a.in1) j = 0;
  }
  a.i0 = i;
  a.i1 = j;
  return a;
}

// The four taps of a bilinear read: flat texel index, whether it is a
// texel (not the border constant), the fractions and the fold slopes.
struct Bilinear {
  int64_t idx[4];
  bool inside[4];
  double fx, fy, sx, sy;
};

DT_INLINE Bilinear taps_folded(Folded u, Folded v, int64_t h, int64_t w, int wrap_u, int wrap_v) {
  Axis ax = place(u, w, wrap_u), ay = place(v, h, wrap_v);
  Bilinear b;
  b.fx = ax.f; b.fy = ay.f; b.sx = ax.slope; b.sy = ay.slope;
  b.idx[0] = ay.i0 * w + ax.i0; b.inside[0] = ay.in0 && ax.in0;
  b.idx[1] = ay.i0 * w + ax.i1; b.inside[1] = ay.in0 && ax.in1;
  b.idx[2] = ay.i1 * w + ax.i0; b.inside[2] = ay.in1 && ax.in0;
  b.idx[3] = ay.i1 * w + ax.i1; b.inside[3] = ay.in1 && ax.in1;
  return b;
}

struct Level {
  int64_t h, w, plane;  // plane = h * w, the channel stride
};

// Levels read by a point and their weights: (level, weight, d weight / dD).
struct Reads {
  int n;
  int64_t k[2];
  double wt[2], dwt[2];
};

DT_INLINE Reads reads_of(double d, int64_t K, bool nearest, bool d_grad) {
  Reads r;
  if (nearest) {
    double k = floor_capped(d + 0.5);
    k = k < 0 ? 0 : (k > K - 1 ? K - 1 : k);
    r.n = 1; r.k[0] = static_cast<int64_t>(k); r.wt[0] = 1.0; r.dwt[0] = 0.0;
    return r;
  }
  double k0 = floor_capped(d);
  k0 = k0 < 0 ? 0 : (k0 > K - 1 ? K - 1 : k0);
  double t = d - k0;
  r.n = 1; r.k[0] = static_cast<int64_t>(k0); r.wt[0] = 1.0 - t; r.dwt[0] = -1.0;
  if (k0 < K - 1 && (d > k0 || (d_grad && d > 0))) {
    r.n = 2; r.k[1] = r.k[0] + 1; r.wt[1] = t; r.dwt[1] = 1.0;
  }
  return r;
}

std::vector<Level> shapes(const std::vector<torch::Tensor>& levels, const torch::Tensor& uv, const torch::Tensor& D,
                          const torch::Tensor& axis, const torch::Tensor& count) {
  TORCH_CHECK(!levels.empty(), "mip_read: no levels");
  const int64_t M = uv.size(0);
  TORCH_CHECK(uv.dim() == 2 && uv.size(1) == 2 && uv.is_contiguous(), "mip_read: uv must be contiguous [M, 2]");
  TORCH_CHECK(D.dim() == 1 && D.size(0) == M && D.scalar_type() == uv.scalar_type() && D.is_contiguous(),
              "mip_read: D must be contiguous [M] of uv's dtype");
  TORCH_CHECK(count.numel() == 0 || (count.dim() == 1 && count.size(0) == M && count.is_contiguous() &&
                                     count.scalar_type() == torch::kInt64 && axis.sizes() == uv.sizes() &&
                                     axis.is_contiguous() && axis.scalar_type() == uv.scalar_type()),
              "mip_read: count must be contiguous int64 [M] and axis contiguous [M, 2] (or both empty)");
  std::vector<Level> out;
  int64_t C = levels[0].size(0);
  for (const auto& t : levels) {
    TORCH_CHECK(t.dim() == 3 && t.size(0) == C && t.is_contiguous() && t.scalar_type() == uv.scalar_type() &&
                    t.device().is_cpu(), "mip_read: levels must be contiguous CPU [C, h, w] of uv's dtype");
    out.push_back({t.size(1), t.size(2), t.size(1) * t.size(2)});
  }
  return out;
}

// Taps of point e: N = count[e] (1 without counts) at uv + o_i * axis,
// o_i = (i + 1/2) / N - 1/2, each weighted 1 / N (filters/anisotropic.py).
inline int64_t tap_count(const int64_t* pc, int64_t e) { return pc == nullptr ? 1 : (pc[e] < 1 ? 1 : pc[e]); }
inline double tap_offset(int64_t i, int64_t N) { return (static_cast<double>(i) + 0.5) / static_cast<double>(N) - 0.5; }

// Runs f(std::integral_constant<int, CC>, std::bool_constant<kBorder>) for
// the channel count (1, 3, 4 fixed at compile time, others at run time)
// and whether either axis reads the border constant.
template <typename F>
void specialized(int64_t C, int64_t wrap_u, int64_t wrap_v, F&& f) {
  auto with_border = [&](auto cc) {
    if (wrap_u == BORDER || wrap_v == BORDER)
      f(cc, std::true_type());
    else
      f(cc, std::false_type());
  };
  switch (C) {
    case 1: with_border(std::integral_constant<int, 1>()); break;
    case 3: with_border(std::integral_constant<int, 3>()); break;
    case 4: with_border(std::integral_constant<int, 4>()); break;
    default: with_border(std::integral_constant<int, 0>());
  }
}

// The forward over points [lo, hi); CC > 0 fixes the channel count at
// compile time (accumulators in registers), 0 takes it at run time.
template <typename scalar_t, int CC, bool kBorder>
void forward_range(int64_t lo, int64_t hi, int64_t Cdyn, const std::vector<Level>& L,
                   const std::vector<const scalar_t*>& lp, const scalar_t* puv, const scalar_t* pd,
                   const int64_t* pc, const scalar_t* pa, scalar_t* po, int64_t M, int64_t wrap_u, int64_t wrap_v,
                   double border, bool nearest, bool d_grad) {
  const int64_t C = CC > 0 ? CC : Cdyn, K = static_cast<int64_t>(L.size());
  std::vector<scalar_t> heap(CC > 0 ? 0 : C);
  scalar_t stack[CC > 0 ? CC : 1];
  scalar_t* acc = CC > 0 ? stack : heap.data();
  for (int64_t e = lo; e < hi; ++e) {
    double u = puv[2 * e], v = puv[2 * e + 1];
    if (!std::isfinite(u) || !std::isfinite(v)) {
      for (int64_t c = 0; c < C; ++c) po[c * M + e] = std::numeric_limits<scalar_t>::quiet_NaN();
      continue;
    }
    Reads r = reads_of(static_cast<double>(pd[e]), K, nearest, d_grad);
    const int64_t N = tap_count(pc, e);
    for (int64_t c = 0; c < C; ++c) acc[c] = 0.0;
    for (int64_t i = 0; i < N; ++i) {
      double o = pc ? tap_offset(i, N) : 0.0;
      double tu = pc ? u + o * pa[2 * e] : u, tv = pc ? v + o * pa[2 * e + 1] : v;
      const Folded fu = fold(tu, wrap_u), fv = fold(tv, wrap_v);
      for (int j = 0; j < r.n; ++j) {
        const Level& lv = L[r.k[j]];
        Bilinear b = taps_folded(fu, fv, lv.h, lv.w, wrap_u, wrap_v);
        const double wl = r.wt[j];
        const scalar_t wts[4] = {static_cast<scalar_t>(wl * (1 - b.fx) * (1 - b.fy)), static_cast<scalar_t>(wl * b.fx * (1 - b.fy)),
                                 static_cast<scalar_t>(wl * (1 - b.fx) * b.fy), static_cast<scalar_t>(wl * b.fx * b.fy)};
        const scalar_t* p = lp[r.k[j]];
        const scalar_t bv = static_cast<scalar_t>(border);
        for (int64_t c = 0; c < C; ++c) {
          const scalar_t* pp = p + c * lv.plane;
          scalar_t s = 0;
          for (int q = 0; q < 4; ++q) s += wts[q] * (!kBorder || b.inside[q] ? pp[b.idx[q]] : bv);
          acc[c] += s;
        }
      }
    }
    for (int64_t c = 0; c < C; ++c) po[c * M + e] = acc[c] / static_cast<scalar_t>(N);
  }
}

torch::Tensor forward(std::vector<torch::Tensor> levels, torch::Tensor uv, torch::Tensor D, torch::Tensor axis,
                      torch::Tensor count, int64_t wrap_u, int64_t wrap_v, double border, bool nearest,
                      bool d_grad) {
  auto L = shapes(levels, uv, D, axis, count);
  const int64_t C = levels[0].size(0), M = uv.size(0);
  auto out = torch::empty({C, M}, uv.options());
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_forward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.data_ptr<scalar_t>());
    const scalar_t* puv = uv.data_ptr<scalar_t>();
    const scalar_t* pd = D.data_ptr<scalar_t>();
    const int64_t* pc = count.numel() ? count.data_ptr<int64_t>() : nullptr;
    const scalar_t* pa = pc ? axis.data_ptr<scalar_t>() : nullptr;
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
      specialized(C, wrap_u, wrap_v, [&](auto cc, auto border_) {
        forward_range<scalar_t, decltype(cc)::value, decltype(border_)::value>(
            lo, hi, C, L, lp, puv, pd, pc, pa, po, M, wrap_u, wrap_v, border, nearest, d_grad);
      });
    });
  });
  return out;
}

// The backward's outputs: level gradients (allocated on first read when
// need_levels) and pointers into the others (null where not needed).
template <typename scalar_t>
struct Grads {
  bool need_levels;
  std::vector<torch::Tensor>* levels;
  scalar_t *uv, *D, *axis;
};

// The backward over all points (serial: the texture gradient is a scatter,
// and points share texels); CC and kBorder as in forward_range.
template <typename scalar_t, int CC, bool kBorder>
void backward_points(int64_t Cdyn, const std::vector<torch::Tensor>& levels, const std::vector<Level>& L,
                     const std::vector<const scalar_t*>& lp, const scalar_t* puv, const scalar_t* pd,
                     const int64_t* pc, const scalar_t* pa, const scalar_t* pg, const Grads<scalar_t>& out, int64_t M,
                     int64_t wrap_u, int64_t wrap_v, double border, bool nearest, bool d_grad) {
  const int64_t C = CC > 0 ? CC : Cdyn, K = static_cast<int64_t>(L.size());
  const bool need_levels = out.need_levels;
  std::vector<scalar_t*> gp(K, nullptr);
  const scalar_t bv = static_cast<scalar_t>(border);
  std::vector<scalar_t> heap(CC > 0 ? 0 : C);
  scalar_t stack[CC > 0 ? CC : 1];
  scalar_t* g = CC > 0 ? stack : heap.data();
  for (int64_t e = 0; e < M; ++e) {
    double u = puv[2 * e], v = puv[2 * e + 1];
    if (!std::isfinite(u) || !std::isfinite(v)) continue;
    Reads r = reads_of(static_cast<double>(pd[e]), K, nearest, d_grad);
    const int64_t N = tap_count(pc, e);
    bool any = false;
    for (int64_t c = 0; c < C; ++c) {
      g[c] = pg[c * M + e] / static_cast<scalar_t>(N);
      any = any || g[c] != 0;
    }
    if (!any) continue;
    double du = 0, dv = 0, dD = 0, dax = 0, day = 0;
    for (int64_t i = 0; i < N; ++i) {
      double o = pc ? tap_offset(i, N) : 0.0;
      double tu = pc ? u + o * pa[2 * e] : u, tv = pc ? v + o * pa[2 * e + 1] : v;
      const Folded fu = fold(tu, wrap_u), fv = fold(tv, wrap_v);
      double tdu = 0, tdv = 0;
      for (int j = 0; j < r.n; ++j) {
        const int64_t k = r.k[j];
        const Level& lv = L[k];
        Bilinear b = taps_folded(fu, fv, lv.h, lv.w, wrap_u, wrap_v);
        const scalar_t fx = static_cast<scalar_t>(b.fx), fy = static_cast<scalar_t>(b.fy);
        const scalar_t w[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
        const scalar_t wl = static_cast<scalar_t>(r.wt[j]);
        const scalar_t* p = lp[k];
        if (need_levels && gp[k] == nullptr) {
          (*out.levels)[k] = torch::zeros_like(levels[k]);
          gp[k] = (*out.levels)[k].template data_ptr<scalar_t>();
        }
        scalar_t sx = 0, sy = 0, sv = 0;
        for (int64_t c = 0; c < C; ++c) {
          const scalar_t* pp = p + c * lv.plane;
          scalar_t t[4];
          for (int q = 0; q < 4; ++q) t[q] = !kBorder || b.inside[q] ? pp[b.idx[q]] : bv;
          sx += g[c] * ((1 - fy) * (t[1] - t[0]) + fy * (t[3] - t[2]));
          sy += g[c] * ((1 - fx) * (t[2] - t[0]) + fx * (t[3] - t[1]));
          sv += g[c] * (w[0] * t[0] + w[1] * t[1] + w[2] * t[2] + w[3] * t[3]);
          if (need_levels) {
            scalar_t* gq = gp[k] + c * lv.plane;
            const scalar_t gw = g[c] * wl;
            for (int q = 0; q < 4; ++q)
              if (!kBorder || b.inside[q]) gq[b.idx[q]] += gw * w[q];
          }
        }
        tdu += r.wt[j] * sx * b.sx * static_cast<double>(lv.w);
        tdv += r.wt[j] * sy * b.sy * static_cast<double>(lv.h);
        dD += r.dwt[j] * sv;
      }
      du += tdu;
      dv += tdv;
      dax += o * tdu;
      day += o * tdv;
    }
    if (out.uv) {
      out.uv[2 * e] = static_cast<scalar_t>(du);
      out.uv[2 * e + 1] = static_cast<scalar_t>(dv);
    }
    if (out.D) out.D[e] = static_cast<scalar_t>(dD);
    if (out.axis) {
      out.axis[2 * e] = static_cast<scalar_t>(dax);
      out.axis[2 * e + 1] = static_cast<scalar_t>(day);
    }
  }
}

// Gradients: (one per level, undefined where no point reads it or not
// needed; uv [M, 2]; D [M]; axis [M, 2]), undefined where not needed.
std::tuple<std::vector<torch::Tensor>, torch::Tensor, torch::Tensor, torch::Tensor> backward(
    std::vector<torch::Tensor> levels, torch::Tensor uv, torch::Tensor D, torch::Tensor axis, torch::Tensor count,
    torch::Tensor grad, int64_t wrap_u, int64_t wrap_v, double border, bool nearest, bool d_grad, bool need_levels,
    bool need_uv, bool need_D, bool need_axis) {
  auto L = shapes(levels, uv, D, axis, count);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(0), M = uv.size(0);
  grad = grad.contiguous();
  TORCH_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == uv.scalar_type(),
              "mip_read: grad must be [C, M] of uv's dtype");
  need_axis = need_axis && count.numel();
  std::vector<torch::Tensor> gl(K);
  torch::Tensor guv = need_uv ? torch::zeros({M, 2}, uv.options()) : torch::Tensor();
  torch::Tensor gD = need_D ? torch::zeros({M}, uv.options()) : torch::Tensor();
  torch::Tensor gax = need_axis ? torch::zeros({M, 2}, uv.options()) : torch::Tensor();
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_backward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.data_ptr<scalar_t>());
    Grads<scalar_t> out;
    out.need_levels = need_levels;
    out.levels = &gl;
    out.uv = need_uv ? guv.data_ptr<scalar_t>() : nullptr;
    out.D = need_D ? gD.data_ptr<scalar_t>() : nullptr;
    out.axis = need_axis ? gax.data_ptr<scalar_t>() : nullptr;
    const int64_t* pc = count.numel() ? count.data_ptr<int64_t>() : nullptr;
    specialized(C, wrap_u, wrap_v, [&](auto cc, auto border_) {
      backward_points<scalar_t, decltype(cc)::value, decltype(border_)::value>(
          C, levels, L, lp, uv.data_ptr<scalar_t>(), D.data_ptr<scalar_t>(), pc, pc ? axis.data_ptr<scalar_t>() : nullptr,
          grad.data_ptr<scalar_t>(), out, M, wrap_u, wrap_v, border, nearest, d_grad);
    });
  });
  return {gl, guv, gD, gax};
}

// The footprint front end of the bilinear-tap mip filters, without
// gradients (difftex/sample.py _taps uses it where no derivative or bias
// needs one): per point, in double, what lod.py's log2_length / footprint
// / ellipse / level and the tap counts of filters/anisotropic.py and
// filters/auto.py give, in one pass instead of 15-50 elementwise torch
// ops. kind 0: trilinear / nearest-mip (the longer footprint vector), 1:
// anisotropic, 2: auto. Returns D [M] clamped to [0, levels - 1] and, for
// kinds 1 and 2, the tap axis [M, 2] in uv (0 for one tap) and the tap
// count [M] (int64). Degenerate footprints as lod.py: NaN or zero
// derivatives are a point (level 0), infinite ones the whole texture (the
// top level), one tap each; a NaN sum with the bias gives level 0.
constexpr double kFar = 1.0e4;   // lod.py _FAR: log2 of a zero / infinite length
constexpr double kRatioTol = 1e-4;  // filters/anisotropic.py _RATIO_TOL
constexpr double kMaxRatio = 18446744073709551616.0;  // 2^64: filters/auto.py _MAX_LOG2 (its floor of
                                                      // half a texel, _LOG2_FLOOR = -1, is the 2^(bias + 1) below)

struct Taps {
  double D, ax, ay;
  int64_t n;
};

inline double clamp_level(double x, int64_t levels) {
  if (std::isnan(x)) return 0.0;
  return x < 0 ? 0.0 : (x > levels - 1 ? static_cast<double>(levels - 1) : x);
}

// lod.py log2_length + level: squares unscaled (in double no float input
// overflows); NaN wins over inf, as torch.maximum does there.
DT_INLINE double trilinear_level(double dx0, double dx1, double dy0, double dy1, double bias, double H, double W,
                                 int64_t levels) {
  const double a = dx0 * W, b = dx1 * H, c = dy0 * W, d = dy1 * H;
  const double p2 = a * a + b * b, q2 = c * c + d * d;
  if (std::isnan(p2) || std::isnan(q2)) return clamp_level(-kFar + bias, levels);
  const double len2 = std::max(p2, q2);
  return clamp_level((len2 == 0 ? -kFar : (std::isinf(len2) ? kFar : 0.5 * std::log2(len2))) + bias, levels);
}

// exp2_bias1: 2^(bias + 1) for auto, or -1 for "not yet computed" (a
// per-point bias); inv_h, inv_w: 1 / H, 1 / W; shrink: 1 / (1 + tolerance).
DT_INLINE Taps front_one(double dx0, double dx1, double dy0, double dy1, double bias, double exp2_bias1, double H,
                         double W, double inv_h, double inv_w, int64_t levels, bool is_auto, double cap,
                         double shrink) {
  const double j0 = dx0 * W, j1 = dx1 * H, j2 = dy0 * W, j3 = dy1 * H;
  Taps t{0.0, 0.0, 0.0, 1};
  const double top = std::max(std::max(std::abs(j0), std::abs(j1)), std::max(std::abs(j2), std::abs(j3)));
  if (!(top > 0) || std::isinf(top)) {
    // A point (zero or NaN derivatives) or the whole texture (infinite
    // ones, NaN winning): one tap at that end of the pyramid.
    const bool nan = std::isnan(j0) || std::isnan(j1) || std::isnan(j2) || std::isnan(j3);
    t.D = clamp_level((std::isinf(top) && !nan ? kFar : -kFar) + bias, levels);
    return t;
  }
  // footprint / ellipse on J / max |J_ij| (lod.py)
  const double r = 1.0 / top, p0 = j0 * r, p1 = j1 * r, q0 = j2 * r, q1 = j3 * r;
  const double a = p0 * p0 + q0 * q0, c = p1 * p1 + q1 * q1, b = p0 * p1 + q0 * q1, hd = 0.5 * (a - c);
  const double disc = std::sqrt(hd * hd + b * b), lam = 0.5 * (a + c) + disc;
  const double major = std::sqrt(lam);  // > 0: one of p, q has an entry of magnitude 1
  // minor = min(det / major, major), so major / minor = max(major^2 / det, 1)
  const double det = std::abs(p0 * q1 - q0 * p1);
  // tap_count (ceil as -floor(-x): the library call is slow without SSE4.1)
  const double q = det > 0 ? std::max(lam / det, 1.0) : cap;
  double n = std::min(std::max(-floor_capped(kRatioTol - q), 1.0), cap);
  if (is_auto && n > 1) {  // (auto never takes more taps than tap_count)
    // auto_tap_count: ratio = 2^(log2 major' - max(log2 minor', -1)) with
    // x' = x 2^bias, in linear form (exp2_bias1 = 2^(bias + 1)); a
    // non-finite bias gives NaN or 0 there, i.e. one tap.
    double m = 1.0;
    if (std::isfinite(bias)) {
      if (exp2_bias1 < 0) exp2_bias1 = std::exp2(bias + 1.0);
      const double minor = std::min(det / major, major);
      const double ratio = minor * top * exp2_bias1 >= 1.0 ? q : major * top * exp2_bias1;
      const double full = std::min(-floor_capped(kRatioTol - std::min(ratio, kMaxRatio)), cap);
      m = ratio > cap ? full : -floor_capped(kRatioTol - full * shrink);
      m = std::min(std::max(m, 1.0), cap);
    }
    n = std::min(n, m);
  }
  t.n = static_cast<int64_t>(n);
  t.D = clamp_level(std::log2(major * top / n) + bias, levels);  // major * top > 0 and finite
  if (t.n > 1) {
    // The major axis as a uv vector: the eigenvector of J J^T = [a b; b c]
    // for lam, oriented as lod.py's angle 0.5 atan2(2b, a - c) (x >= 0).
    double ex = a >= c ? lam - c : b, ey = a >= c ? b : lam - a;
    const double s = (ex < 0 ? -major * top : major * top) / std::sqrt(ex * ex + ey * ey);
    t.ax = ex * s * inv_w;
    t.ay = ey * s * inv_h;
  }
  return t;
}

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> front(torch::Tensor dx, torch::Tensor dy, torch::Tensor bias,
                                                              double bias0, int64_t H, int64_t W, int64_t levels,
                                                              int64_t kind, double max_aniso, double tolerance) {
  const int64_t M = dx.size(0);
  TORCH_CHECK(dx.dim() == 2 && dx.size(1) == 2 && dx.is_contiguous() && dx.device().is_cpu() &&
                  dy.sizes() == dx.sizes() && dy.is_contiguous() && dy.scalar_type() == dx.scalar_type(),
              "mip_read.front: uv_dx, uv_dy must be contiguous CPU [M, 2] of one dtype");
  TORCH_CHECK(bias.numel() == 0 || (bias.dim() == 1 && bias.size(0) == M && bias.is_contiguous() &&
                                    bias.scalar_type() == dx.scalar_type()),
              "mip_read.front: bias must be contiguous [M] of uv_dx's dtype, or empty");
  TORCH_CHECK(levels >= 1 && kind >= 0 && kind <= 2, "mip_read.front: levels >= 1, kind 0, 1 or 2");
  const bool is_auto = kind == 2;
  const double cap = std::max(std::floor(max_aniso), 1.0), exp2_bias0 = std::exp2(bias0 + 1.0);
  const double shrink = 1.0 / (1.0 + tolerance);
  auto D = torch::empty({M}, dx.options());
  auto axis = torch::empty({kind ? M : 0, 2}, dx.options());
  auto count = torch::empty({kind ? M : 0}, dx.options().dtype(torch::kInt64));
  AT_DISPATCH_FLOATING_TYPES(dx.scalar_type(), "mip_read_front", [&] {
    const scalar_t* px = dx.data_ptr<scalar_t>();
    const scalar_t* py = dy.data_ptr<scalar_t>();
    const scalar_t* pb = bias.numel() ? bias.data_ptr<scalar_t>() : nullptr;
    scalar_t* pD = D.data_ptr<scalar_t>();
    scalar_t* pa = axis.data_ptr<scalar_t>();
    int64_t* pn = count.data_ptr<int64_t>();
    const double h = static_cast<double>(H), w = static_cast<double>(W);
    at::parallel_for(0, M, 2048, [&](int64_t lo, int64_t hi) {
      for (int64_t e = lo; e < hi; ++e) {
        const double b = pb ? static_cast<double>(pb[e]) : bias0;
        if (kind == 0) {
          pD[e] = static_cast<scalar_t>(trilinear_level(px[2 * e], px[2 * e + 1], py[2 * e], py[2 * e + 1], b, h, w,
                                                        levels));
          continue;
        }
        Taps t = front_one(px[2 * e], px[2 * e + 1], py[2 * e], py[2 * e + 1], b, pb ? -1.0 : exp2_bias0, h, w,
                           1.0 / h, 1.0 / w, levels, is_auto, cap, shrink);
        pD[e] = static_cast<scalar_t>(t.D);
        pa[2 * e] = static_cast<scalar_t>(t.ax);
        pa[2 * e + 1] = static_cast<scalar_t>(t.ay);
        pn[e] = t.n;
      }
    });
  });
  return {D, axis, count};
}

// One 2 x 2 box step of an even x even level (difftex/mipmap.py _box2, the
// same sums in the same order, so bit-identical): [..., H, W] -> [..., H/2,
// W/2]. One pass over the level instead of torch's three (two strided adds
// and a scale): about half the memory traffic of the pyramid build.
torch::Tensor box2(torch::Tensor x) {
  TORCH_CHECK(x.dim() >= 2 && x.size(-2) % 2 == 0 && x.size(-1) % 2 == 0 && x.device().is_cpu(),
              "mip_read.box2: expected a CPU tensor [..., H, W] with even H and W");
  x = x.contiguous();
  const int64_t H = x.size(-2), W = x.size(-1), h = H / 2, w = W / 2;
  auto sizes = x.sizes().vec();
  sizes[sizes.size() - 2] = h;
  sizes[sizes.size() - 1] = w;
  auto out = torch::empty(sizes, x.options());
  const int64_t rows = x.numel() / W / 2;  // output rows over every plane
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "mip_read_box2", [&] {
    const scalar_t* px = x.data_ptr<scalar_t>();
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, rows, 16, [&](int64_t lo, int64_t hi) {
      for (int64_t r = lo; r < hi; ++r) {
        const scalar_t* a = px + 2 * r * W;
        const scalar_t* b = a + W;
        scalar_t* o = po + r * w;
        for (int64_t j = 0; j < w; ++j)
          o[j] = ((a[2 * j] + a[2 * j + 1]) + (b[2 * j] + b[2 * j + 1])) * static_cast<scalar_t>(0.25);
      }
    });
  });
  return out;
}

// An integral double as int64, capped at +-2^52 (wrap.py floor_index).
DT_INLINE int64_t index_of(double x) {
  return static_cast<int64_t>(x < -kTwo52 ? -kTwo52 : (x > kTwo52 ? kTwo52 : x));
}

// Integer texel index of one axis wrapped into [0, n) as wrap.py's
// wrap_index; false where "border" reads the constant instead.
DT_INLINE bool wrap_int(int64_t i, int64_t n, int mode, int64_t* out) {
  if (i >= 0 && i < n) {  // inside: every mode reads i (and no integer division)
    *out = i;
    return true;
  }
  switch (mode) {
    case REPEAT: {
      int64_t r = i % n;
      *out = r < 0 ? r + n : r;
      return true;
    }
    case MIRROR: {
      int64_t r = i % (2 * n);
      r = r < 0 ? r + 2 * n : r;
      *out = r >= n ? 2 * n - 1 - r : r;
      return true;
    }
    case CLAMP:
      *out = i < 0 ? 0 : (i >= n ? n - 1 : i);
      return true;
    default:
      *out = i < 0 ? 0 : (i >= n ? n - 1 : i);
      return i >= 0 && i < n;
  }
}

// EWA (filters/ewa.py, its reference, which also serves CUDA and double
// backward): per point the blend of levels floor(D) and floor(D) + 1
// (mip_blend's weights and reads), each the Gaussian-weighted mean of the
// texels inside the padded ellipse as _ewa_level and _pairs compute it, in
// double. Inputs: uv [M, 2] the points with whole periods dropped (finite);
// sigma [M, 3] the scaled J J^T with the minor axis grown; minor [M] that
// axis (scaled); scale [M] the footprint scale; D [M] the clamped level;
// levels [C, h, w].
constexpr double kAlpha = 2.0;  // filters/ewa.py _ALPHA (and _MAX_MINOR = 2 below)

// One point's ellipse on level k, in level-k texels (_ewa_level).
struct EwaSetup {
  double kx, ky, s, sxx, sxy, syy, det, ox, oy, sx, sy;
  bool capped;  // s = cap / minor_k (else s = scale)
};

template <typename scalar_t>
DT_INLINE EwaSetup ewa_setup(const Level& lv, bool coarsest, int64_t full_h, int64_t full_w, const scalar_t* uv,
                             const scalar_t* sigma, double minor, double scale) {
  EwaSetup q;
  const double hk = static_cast<double>(lv.h), wk = static_cast<double>(lv.w);
  q.kx = wk / static_cast<double>(full_w);
  q.ky = hk / static_cast<double>(full_h);
  const double cap = coarsest ? 2.0 : std::max(2.0, std::max(hk, wk));
  const double minor_k = minor * std::max(q.kx, q.ky);
  q.capped = minor_k > 0 && cap / minor_k < scale;
  q.s = q.capped ? cap / minor_k : scale;
  const double s2 = q.s * q.s;
  q.sxx = static_cast<double>(sigma[0]) * (s2 * q.kx * q.kx) + 1;
  q.sxy = static_cast<double>(sigma[1]) * (s2 * q.kx * q.ky);
  q.syy = static_cast<double>(sigma[2]) * (s2 * q.ky * q.ky) + 1;
  q.det = q.sxx * q.syy - q.sxy * q.sxy;
  const double posx = static_cast<double>(uv[0]) * wk - 0.5, posy = static_cast<double>(uv[1]) * hk - 0.5;
  // Integer origin + fraction (no fraction left from 2^52 on, as in torch).
  q.ox = std::abs(posx) < kTwo52 ? floor_capped(posx) : posx;
  q.oy = std::abs(posy) < kTwo52 ? floor_capped(posy) : posy;
  q.sx = posx - q.ox;
  q.sy = posy - q.oy;
  return q;
}

// Calls f(ss, tt, r2, w, texel offset or -1 for the border constant) for
// every texel centre inside the ellipse (_pairs' rows and runs).
template <typename F>
DT_INLINE void ewa_texels(const EwaSetup& q, const Level& lv, int wrap_u, int wrap_v, F&& f) {
  const double floor_w = std::exp(-kAlpha), hy = std::sqrt(q.syy);
  const double r0 = -floor_capped(-(q.sy - hy));
  const int64_t rows = std::max<int64_t>(static_cast<int64_t>(floor_capped(q.sy + hy) - r0 + 1), 0);
  for (int64_t i = 0; i < rows; ++i) {
    const double ry = r0 + static_cast<double>(i), tt = ry - q.sy;
    const double centre = q.sx + q.sxy / q.syy * tt;
    const double half = std::sqrt(std::max(q.det / q.syy * (1 - tt * tt / q.syy), 0.0));
    const double c0 = -floor_capped(-(centre - half));
    const int64_t cols = std::max<int64_t>(static_cast<int64_t>(floor_capped(centre + half) - c0 + 1), 0);
    int64_t iy;
    const bool vy = wrap_int(index_of(q.oy + ry), lv.h, wrap_v, &iy);
    for (int64_t j = 0; j < cols; ++j) {
      const double rx = c0 + static_cast<double>(j), ss = rx - q.sx;
      const double r2 = (q.syy * ss * ss - 2 * q.sxy * ss * tt + q.sxx * tt * tt) / q.det;
      const double w = std::max(std::exp(-kAlpha * r2) - floor_w, 0.0);
      int64_t ix;
      const bool vx = wrap_int(index_of(q.ox + rx), lv.w, wrap_u, &ix);
      f(ss, tt, r2, w, vx && vy ? iy * lv.w + ix : -1);
    }
  }
}

// A texel with a positive EWA weight, as ewa_texels reports it.
struct EwaTexel {
  double ss, tt, r2, w;
  int64_t at;
};

// One level's EWA value: num[c] = sum of w * texel, returns den = sum of w
// (the value is num / den). With kept, also the texels of positive weight
// (the backward's second pass walks them instead of the ellipse again).
template <typename scalar_t>
DT_INLINE double ewa_sums(const EwaSetup& q, const Level& lv, const scalar_t* p, int64_t C, int wrap_u, int wrap_v,
                          double border, std::vector<double>& num, std::vector<EwaTexel>* kept = nullptr) {
  std::fill(num.begin(), num.end(), 0.0);
  if (kept) kept->clear();
  double den = 0;
  ewa_texels(q, lv, wrap_u, wrap_v, [&](double ss, double tt, double r2, double w, int64_t at) {
    for (int64_t c = 0; c < C; ++c) num[c] += w * (at >= 0 ? static_cast<double>(p[c * lv.plane + at]) : border);
    den += w;
    if (kept && w > 0) kept->push_back({ss, tt, r2, w, at});
  });
  return den;
}

void ewa_checks(const torch::Tensor& uv, const torch::Tensor& sigma, const torch::Tensor& minor,
                const torch::Tensor& scale) {
  const int64_t M = uv.size(0);
  TORCH_CHECK(sigma.dim() == 2 && sigma.size(0) == M && sigma.size(1) == 3 && sigma.is_contiguous() &&
                  minor.dim() == 1 && minor.size(0) == M && minor.is_contiguous() && scale.dim() == 1 &&
                  scale.size(0) == M && scale.is_contiguous() && sigma.scalar_type() == uv.scalar_type() &&
                  minor.scalar_type() == uv.scalar_type() && scale.scalar_type() == uv.scalar_type(),
              "mip_read.ewa: sigma [M, 3], minor [M], scale [M] contiguous, of uv's dtype");
}

// Forward: [C, M]. d_grad: D needs a gradient (the upper level is read at
// an integer D too, as mip_blend does).
torch::Tensor ewa(std::vector<torch::Tensor> levels, torch::Tensor uv, torch::Tensor sigma, torch::Tensor minor,
                  torch::Tensor scale, torch::Tensor D, int64_t full_h, int64_t full_w, int64_t wrap_u,
                  int64_t wrap_v, double border, bool d_grad) {
  auto L = shapes(levels, uv, D, torch::empty({0}, uv.options()), torch::empty({0}, uv.options().dtype(torch::kInt64)));
  ewa_checks(uv, sigma, minor, scale);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(0), M = uv.size(0);
  auto out = torch::empty({C, M}, uv.options());
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_ewa", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.data_ptr<scalar_t>());
    const scalar_t *puv = uv.data_ptr<scalar_t>(), *ps = sigma.data_ptr<scalar_t>();
    const scalar_t *pm = minor.data_ptr<scalar_t>(), *psc = scale.data_ptr<scalar_t>(), *pd = D.data_ptr<scalar_t>();
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, M, 256, [&](int64_t lo, int64_t hi) {
      std::vector<double> num(C), acc(C);
      for (int64_t e = lo; e < hi; ++e) {
        Reads r = reads_of(static_cast<double>(pd[e]), K, false, d_grad);
        std::fill(acc.begin(), acc.end(), 0.0);
        for (int j = 0; j < r.n; ++j) {
          const Level& lv = L[r.k[j]];
          const EwaSetup q = ewa_setup(lv, r.k[j] == K - 1, full_h, full_w, puv + 2 * e, ps + 3 * e,
                                       static_cast<double>(pm[e]), static_cast<double>(psc[e]));
          const double den = ewa_sums(q, lv, lp[r.k[j]], C, static_cast<int>(wrap_u), static_cast<int>(wrap_v),
                                      border, num);
          for (int64_t c = 0; c < C; ++c) acc[c] += r.wt[j] * (num[c] / den);
        }
        for (int64_t c = 0; c < C; ++c) po[c * M + e] = static_cast<scalar_t>(acc[c]);
      }
    });
  });
  return out;
}

// First-order backward: (level gradients, undefined where unread or not
// needed; uv [M, 2]; sigma [M, 3]; minor [M]; scale [M]; D [M]); each
// undefined where not needed. The points are split into up to 4 chunks run
// in parallel, each scattering its texture gradient into its own buffers.
std::tuple<std::vector<torch::Tensor>, torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor, torch::Tensor>
ewa_backward(std::vector<torch::Tensor> levels, torch::Tensor uv, torch::Tensor sigma, torch::Tensor minor,
             torch::Tensor scale, torch::Tensor D, torch::Tensor grad, int64_t full_h, int64_t full_w,
             int64_t wrap_u, int64_t wrap_v, double border, bool d_grad, bool need_levels, bool need_uv,
             bool need_ellipse, bool need_D) {
  auto L = shapes(levels, uv, D, torch::empty({0}, uv.options()), torch::empty({0}, uv.options().dtype(torch::kInt64)));
  ewa_checks(uv, sigma, minor, scale);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(0), M = uv.size(0);
  grad = grad.contiguous();
  TORCH_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == uv.scalar_type(),
              "mip_read.ewa_backward: grad must be [C, M] of uv's dtype");
  std::vector<torch::Tensor> gl(K);
  auto opt = uv.options();
  torch::Tensor guv = need_uv ? torch::zeros({M, 2}, opt) : torch::Tensor();
  torch::Tensor gsig = need_ellipse ? torch::zeros({M, 3}, opt) : torch::Tensor();
  torch::Tensor gmin = need_ellipse ? torch::zeros({M}, opt) : torch::Tensor();
  torch::Tensor gsc = need_ellipse ? torch::zeros({M}, opt) : torch::Tensor();
  torch::Tensor gD = need_D ? torch::zeros({M}, opt) : torch::Tensor();
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_ewa_backward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.data_ptr<scalar_t>());
    const scalar_t *puv = uv.data_ptr<scalar_t>(), *ps = sigma.data_ptr<scalar_t>();
    const scalar_t *pm = minor.data_ptr<scalar_t>(), *psc = scale.data_ptr<scalar_t>(), *pd = D.data_ptr<scalar_t>();
    const scalar_t* pg = grad.data_ptr<scalar_t>();
    scalar_t* o_uv = need_uv ? guv.data_ptr<scalar_t>() : nullptr;
    scalar_t* o_sig = need_ellipse ? gsig.data_ptr<scalar_t>() : nullptr;
    scalar_t* o_min = need_ellipse ? gmin.data_ptr<scalar_t>() : nullptr;
    scalar_t* o_sc = need_ellipse ? gsc.data_ptr<scalar_t>() : nullptr;
    scalar_t* o_D = need_D ? gD.data_ptr<scalar_t>() : nullptr;
    // Points [lo, hi) scattering their texture gradient into gp (one
    // buffer set per chunk of points, so that chunks run in parallel).
    auto run = [&](int64_t lo, int64_t hi, const std::vector<scalar_t*>& gp) {
      std::vector<double> num(C), out(C), g(C);
      std::vector<EwaTexel> kept;
      const double floor_w = std::exp(-kAlpha);
      for (int64_t e = lo; e < hi; ++e) {
        Reads r = reads_of(static_cast<double>(pd[e]), K, false, d_grad);
        double gu = 0, gv = 0, gs0 = 0, gs1 = 0, gs2 = 0, gm = 0, gscale = 0, gd = 0;
        for (int j = 0; j < r.n; ++j) {
          const int64_t k = r.k[j];
          const Level& lv = L[k];
          const EwaSetup q = ewa_setup(lv, k == K - 1, full_h, full_w, puv + 2 * e, ps + 3 * e,
                                       static_cast<double>(pm[e]), static_cast<double>(psc[e]));
          const scalar_t* p = lp[k];
          const int wu = static_cast<int>(wrap_u), wv = static_cast<int>(wrap_v);
          // Pass 1: this level's value out = num / den.
          const double den = ewa_sums(q, lv, p, C, wu, wv, border, num, &kept);
          double dot = 0;  // sum_c grad_c * out_c, for d/dD
          for (int64_t c = 0; c < C; ++c) {
            out[c] = num[c] / den;
            g[c] = static_cast<double>(pg[c * M + e]) * r.wt[j];  // d loss / d out (this level)
            dot += static_cast<double>(pg[c * M + e]) * out[c];
          }
          gd += r.dwt[j] * dot;
          // Pass 2: d out_c / d val = w / den; d out_c / d w = (val_c - out_c) / den.
          double gsx = 0, gsy = 0, gxx = 0, gxy = 0, gyy = 0;
          for (const EwaTexel& t : kept) {
            const double ss = t.ss, tt = t.tt, r2 = t.r2, w = t.w;
            const int64_t at = t.at;
            double gw = 0;
            for (int64_t c = 0; c < C; ++c) {
              const double val = at >= 0 ? static_cast<double>(p[c * lv.plane + at]) : border;
              gw += g[c] * (val - out[c]);
              if (need_levels && at >= 0) gp[k][c * lv.plane + at] += static_cast<scalar_t>(g[c] * w / den);
            }
            // w = exp(-alpha r2) - exp(-alpha) (positive here).
            const double gr2 = gw / den * (-kAlpha) * (w + floor_w) / q.det;
            gsx += gr2 * (-2 * q.syy * ss + 2 * q.sxy * tt);
            gsy += gr2 * (2 * q.sxy * ss - 2 * q.sxx * tt);
            gxx += gr2 * (tt * tt - r2 * q.syy);
            gyy += gr2 * (ss * ss - r2 * q.sxx);
            gxy += gr2 * (-2 * ss * tt + 2 * r2 * q.sxy);
          }
          gu += gsx * static_cast<double>(lv.w);
          gv += gsy * static_cast<double>(lv.h);
          // sxx = sigma0 s^2 kx^2 + 1, sxy = sigma1 s^2 kx ky, syy = sigma2 s^2 ky^2 + 1
          const double s2 = q.s * q.s;
          gs0 += gxx * s2 * q.kx * q.kx;
          gs1 += gxy * s2 * q.kx * q.ky;
          gs2 += gyy * s2 * q.ky * q.ky;
          const double g_s = 2 * q.s * (gxx * static_cast<double>(ps[3 * e]) * q.kx * q.kx +
                                        gxy * static_cast<double>(ps[3 * e + 1]) * q.kx * q.ky +
                                        gyy * static_cast<double>(ps[3 * e + 2]) * q.ky * q.ky);
          if (q.capped) {  // s = cap / (minor max(kx, ky))
            gm += -g_s * q.s / static_cast<double>(pm[e]);
          } else {
            gscale += g_s;
          }
        }
        if (o_uv) {
          o_uv[2 * e] = static_cast<scalar_t>(gu);
          o_uv[2 * e + 1] = static_cast<scalar_t>(gv);
        }
        if (o_sig) {
          o_sig[3 * e] = static_cast<scalar_t>(gs0);
          o_sig[3 * e + 1] = static_cast<scalar_t>(gs1);
          o_sig[3 * e + 2] = static_cast<scalar_t>(gs2);
          o_min[e] = static_cast<scalar_t>(gm);
          o_sc[e] = static_cast<scalar_t>(gscale);
        }
        if (o_D) o_D[e] = static_cast<scalar_t>(gd);
      }
    };
    // Level gradients only for the levels some point reads; one set per
    // chunk (at most 4 chunks: each set costs a texture-sized buffer), summed after.
    std::vector<bool> read(K, false);
    for (int64_t e = 0; need_levels && e < M; ++e) {
      Reads r = reads_of(static_cast<double>(pd[e]), K, false, d_grad);
      for (int j = 0; j < r.n; ++j) read[r.k[j]] = true;
    }
    const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>({static_cast<int64_t>(at::get_num_threads()),
                                                                    4, M / 4096}));
    std::vector<std::vector<torch::Tensor>> bufs(chunks, std::vector<torch::Tensor>(K));
    std::vector<std::vector<scalar_t*>> ptrs(chunks, std::vector<scalar_t*>(K, nullptr));
    if (need_levels)
      for (int64_t c = 0; c < chunks; ++c)
        for (int64_t k = 0; k < K; ++k)
          if (read[k]) {
            bufs[c][k] = torch::zeros_like(levels[k]);
            ptrs[c][k] = bufs[c][k].template data_ptr<scalar_t>();
          }
    at::parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) run(c * M / chunks, (c + 1) * M / chunks, ptrs[c]);
    });
    if (need_levels)
      for (int64_t k = 0; k < K; ++k) {
        if (!read[k]) continue;
        for (int64_t c = 1; c < chunks; ++c) bufs[0][k].add_(bufs[c][k]);
        gl[k] = bufs[0][k];
      }
  });
  return {gl, guv, gsig, gmin, gsc, gD};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "mip pyramid read, forward");
  m.def("backward", &backward, "mip pyramid read, first-order backward");
  m.def("ewa", &ewa, "EWA filter, forward");
  m.def("ewa_backward", &ewa_backward, "EWA filter, first-order backward");
  m.def("box2", &box2, "2 x 2 box step of an even level");
  m.def("front", &front, "mip level (and anisotropic / auto tap axis and count), no gradient");
}
