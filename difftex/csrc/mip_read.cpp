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
// their sub-texel position.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace {

enum Wrap { REPEAT = 0, CLAMP = 1, MIRROR = 2, BORDER = 3 };

// floor(x) through an integer truncation (std::floor is a library call
// without SSE4.1, a truncation two instructions). Capped at +-2^52, where
// no fraction is left anyway; NaN gives -2^52 (callers test finiteness).
inline double floor_capped(double x) {
  const double cap = 4503599627370496.0;
  if (!(x > -cap)) return -cap;
  if (!(x < cap)) return cap;
  double t = static_cast<double>(static_cast<int64_t>(x));
  return t > x ? t - 1.0 : t;
}

// x - floor(x) in [0, 1); 0 from 2^52 on, where doubles are integers.
inline double frac(double x) {
  return std::abs(x) < 4503599627370496.0 ? x - floor_capped(x) : 0.0;
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

inline Axis axis(double u, int64_t n, int mode) {
  Axis a;
  a.slope = 1.0;
  a.in0 = a.in1 = true;
  if (mode == REPEAT) {
    u = frac(u);
  } else if (mode == MIRROR) {
    double f = frac(0.5 * u);
    a.slope = f < 0.5 ? 1.0 : -1.0;
    u = 1.0 - std::abs(2.0 * f - 1.0);
  }
  double x = u * static_cast<double>(n) - 0.5, x0 = floor_capped(x);
  a.f = x - x0;
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

inline Bilinear taps(double u, double v, int64_t h, int64_t w, int wrap_u, int wrap_v) {
  Axis ax = axis(u, w, wrap_u), ay = axis(v, h, wrap_v);
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

inline Reads reads_of(double d, int64_t K, bool nearest, bool d_grad) {
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

torch::Tensor forward(std::vector<torch::Tensor> levels, torch::Tensor uv, torch::Tensor D, torch::Tensor axis,
                      torch::Tensor count, int64_t wrap_u, int64_t wrap_v, double border, bool nearest,
                      bool d_grad) {
  auto L = shapes(levels, uv, D, axis, count);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(0), M = uv.size(0);
  auto out = torch::zeros({C, M}, uv.options());
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_forward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.data_ptr<scalar_t>());
    const scalar_t* puv = uv.data_ptr<scalar_t>();
    const scalar_t* pd = D.data_ptr<scalar_t>();
    const int64_t* pc = count.numel() ? count.data_ptr<int64_t>() : nullptr;
    const scalar_t* pa = pc ? axis.data_ptr<scalar_t>() : nullptr;
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
      std::vector<double> acc(C);
      for (int64_t e = lo; e < hi; ++e) {
        double u = puv[2 * e], v = puv[2 * e + 1];
        if (!std::isfinite(u) || !std::isfinite(v)) {
          for (int64_t c = 0; c < C; ++c) po[c * M + e] = std::numeric_limits<scalar_t>::quiet_NaN();
          continue;
        }
        Reads r = reads_of(static_cast<double>(pd[e]), K, nearest, d_grad);
        const int64_t N = tap_count(pc, e);
        std::fill(acc.begin(), acc.end(), 0.0);
        for (int64_t i = 0; i < N; ++i) {
          double o = pc ? tap_offset(i, N) : 0.0;
          double tu = pc ? u + o * pa[2 * e] : u, tv = pc ? v + o * pa[2 * e + 1] : v;
          for (int j = 0; j < r.n; ++j) {
            const Level& lv = L[r.k[j]];
            Bilinear b = taps(tu, tv, lv.h, lv.w, wrap_u, wrap_v);
            double wts[4] = {(1 - b.fx) * (1 - b.fy), b.fx * (1 - b.fy), (1 - b.fx) * b.fy, b.fx * b.fy};
            const scalar_t* p = lp[r.k[j]];
            for (int64_t c = 0; c < C; ++c) {
              const scalar_t* pp = p + c * lv.plane;
              double s = 0;
              for (int q = 0; q < 4; ++q) s += wts[q] * (b.inside[q] ? static_cast<double>(pp[b.idx[q]]) : border);
              acc[c] += r.wt[j] * s;
            }
          }
        }
        for (int64_t c = 0; c < C; ++c) po[c * M + e] = static_cast<scalar_t>(acc[c] / static_cast<double>(N));
      }
    });
  });
  return out;
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
    std::vector<scalar_t*> gp(K, nullptr);
    const scalar_t* puv = uv.data_ptr<scalar_t>();
    const scalar_t* pd = D.data_ptr<scalar_t>();
    const int64_t* pc = count.numel() ? count.data_ptr<int64_t>() : nullptr;
    const scalar_t* pa = pc ? axis.data_ptr<scalar_t>() : nullptr;
    const scalar_t* pg = grad.data_ptr<scalar_t>();
    scalar_t* pguv = need_uv ? guv.data_ptr<scalar_t>() : nullptr;
    scalar_t* pgD = need_D ? gD.data_ptr<scalar_t>() : nullptr;
    scalar_t* pgax = need_axis ? gax.data_ptr<scalar_t>() : nullptr;
    // Serial: the texture gradient is a scatter (points share texels).
    for (int64_t e = 0; e < M; ++e) {
      double u = puv[2 * e], v = puv[2 * e + 1];
      if (!std::isfinite(u) || !std::isfinite(v)) continue;
      Reads r = reads_of(static_cast<double>(pd[e]), K, nearest, d_grad);
      const int64_t N = tap_count(pc, e);
      const double inv = 1.0 / static_cast<double>(N);
      double du = 0, dv = 0, dD = 0, dax = 0, day = 0;
      for (int64_t i = 0; i < N; ++i) {
        double o = pc ? tap_offset(i, N) : 0.0;
        double tu = pc ? u + o * pa[2 * e] : u, tv = pc ? v + o * pa[2 * e + 1] : v;
        double tdu = 0, tdv = 0;
        for (int j = 0; j < r.n; ++j) {
          const int64_t k = r.k[j];
          const Level& lv = L[k];
          Bilinear b = taps(tu, tv, lv.h, lv.w, wrap_u, wrap_v);
          double wts[4] = {(1 - b.fx) * (1 - b.fy), b.fx * (1 - b.fy), (1 - b.fx) * b.fy, b.fx * b.fy};
          const scalar_t* p = lp[k];
          if (need_levels && gp[k] == nullptr) {
            gl[k] = torch::zeros_like(levels[k]);
            gp[k] = gl[k].data_ptr<scalar_t>();
          }
          double sx = 0, sy = 0, sv = 0;
          for (int64_t c = 0; c < C; ++c) {
            double g = static_cast<double>(pg[c * M + e]) * inv;
            if (g == 0) continue;
            const scalar_t* pp = p + c * lv.plane;
            double t[4];
            for (int q = 0; q < 4; ++q) t[q] = b.inside[q] ? static_cast<double>(pp[b.idx[q]]) : border;
            sx += g * ((1 - b.fy) * (t[1] - t[0]) + b.fy * (t[3] - t[2]));
            sy += g * ((1 - b.fx) * (t[2] - t[0]) + b.fx * (t[3] - t[1]));
            sv += g * (wts[0] * t[0] + wts[1] * t[1] + wts[2] * t[2] + wts[3] * t[3]);
            if (need_levels) {
              scalar_t* gq = gp[k] + c * lv.plane;
              for (int q = 0; q < 4; ++q)
                if (b.inside[q]) gq[b.idx[q]] += static_cast<scalar_t>(g * r.wt[j] * wts[q]);
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
      if (need_uv) {
        pguv[2 * e] = static_cast<scalar_t>(du);
        pguv[2 * e + 1] = static_cast<scalar_t>(dv);
      }
      if (need_D) pgD[e] = static_cast<scalar_t>(dD);
      if (need_axis) {
        pgax[2 * e] = static_cast<scalar_t>(dax);
        pgax[2 * e + 1] = static_cast<scalar_t>(day);
      }
    }
  });
  return {gl, guv, gD, gax};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "mip pyramid read, forward");
  m.def("backward", &backward, "mip pyramid read, first-order backward");
}
