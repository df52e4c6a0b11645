// The bilinear-tap mip filters on the CPU (trilinear, nearest-mip,
// anisotropic, auto: filters/trilinear.py _NativeTaps), forward and
// first-order backward, one pass over the points: per point one tap
// (trilinear, nearest-mip) or N taps spread along an axis (anisotropic,
// auto), so no tap list is built, and a backward that touches only the
// texels read, threaded over the points with the level gradients scattered
// by bands of rows (bands.h; the band scales below). Semantics in common.h.
//
// Coordinates are computed in double, so float32 uv far from [0, 1] keep
// their sub-texel position; texel arithmetic is in the texture's dtype (as
// grid_sample's), with the channel count (1, 3, 4) and whether a border
// constant is read fixed at compile time (measured: 20-30% faster than
// double arithmetic with run-time checks, float32, 3 channels).
#include "bands.h"
#include "common.h"
#include "kernels.h"

namespace difftex {

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


namespace {

// Taps of point e: N = count[e] (1 without counts) at uv + o_i * axis,
// o_i = (i + 1/2) / N - 1/2, each weighted 1 / N (filters/anisotropic.py).
inline int64_t tap_count(const int64_t* pc, int64_t e) { return pc == nullptr ? 1 : (pc[e] < 1 ? 1 : pc[e]); }
inline double tap_offset(int64_t i, int64_t N) { return (static_cast<double>(i) + 0.5) / static_cast<double>(N) - 0.5; }

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

}  // namespace

torch::Tensor forward(std::vector<torch::Tensor> levels, torch::Tensor uv, torch::Tensor D, torch::Tensor axis,
                      torch::Tensor count, const ReadOptions& opts) {
  const int64_t wrap_u = opts.wrap_u, wrap_v = opts.wrap_v;
  const double border = opts.border;
  const bool nearest = opts.nearest, d_grad = opts.d_grad;
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

namespace {

// The backward's outputs: level gradients (gp[k]: null where no point
// reads level k or they are not needed) and the others (null where not
// needed).
template <typename scalar_t>
struct Grads {
  std::vector<scalar_t*> gp;
  scalar_t *uv, *D, *axis;
};

// Point e's backward: its uv / D / axis gradients, and its level gradients
// scattered into out.gp; CC and kBorder as in forward_range.
template <typename scalar_t, int CC, bool kBorder>
DT_INLINE void backward_point(int64_t e, int64_t Cdyn, const std::vector<Level>& L,
                              const std::vector<const scalar_t*>& lp, const scalar_t* puv, const scalar_t* pd,
                              const int64_t* pc, const scalar_t* pa, const scalar_t* pg, const Grads<scalar_t>& out,
                              int64_t gsc, int64_t gsm, int64_t wrap_u, int64_t wrap_v, double border, bool nearest,
                              bool d_grad) {
  const int64_t C = CC > 0 ? CC : Cdyn, K = static_cast<int64_t>(L.size());
  const scalar_t bv = static_cast<scalar_t>(border);
  std::vector<scalar_t> heap(CC > 0 ? 0 : C);
  scalar_t stack[CC > 0 ? CC : 1];
  scalar_t* g = CC > 0 ? stack : heap.data();
  double u = puv[2 * e], v = puv[2 * e + 1];
  if (!std::isfinite(u) || !std::isfinite(v)) return;
  Reads r = reads_of(static_cast<double>(pd[e]), K, nearest, d_grad);
  const int64_t N = tap_count(pc, e);
  bool any = false;
  for (int64_t c = 0; c < C; ++c) {
    g[c] = pg[c * gsc + e * gsm] / static_cast<scalar_t>(N);
    any = any || g[c] != 0;
  }
  if (!any) return;
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
      scalar_t* gk = out.gp[k];
      scalar_t sx = 0, sy = 0, sv = 0;
      for (int64_t c = 0; c < C; ++c) {
        const scalar_t* pp = p + c * lv.plane;
        scalar_t t[4];
        for (int q = 0; q < 4; ++q) t[q] = !kBorder || b.inside[q] ? pp[b.idx[q]] : bv;
        sx += g[c] * ((1 - fy) * (t[1] - t[0]) + fy * (t[3] - t[2]));
        sy += g[c] * ((1 - fx) * (t[2] - t[0]) + fx * (t[3] - t[1]));
        sv += g[c] * (w[0] * t[0] + w[1] * t[1] + w[2] * t[2] + w[3] * t[3]);
        if (gk != nullptr) {
          scalar_t* gq = gk + c * lv.plane;
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

// The taps' level-gradient scatter uses bands.h's ScaleBands: a point
// writes rows of up to two levels, around its taps' v range (N taps along
// the axis); the bands are fractions of the texture height, the same on
// every level.

DT_INLINE int64_t floor_div(int64_t a, int64_t b) { return a >= 0 ? a / b : -((-a + b - 1) / b); }

// The rows a point's taps write on a level of h rows, from the range
// [lo, hi] of their v (repeat: unwrapped, within a period of [0, 1)), with
// a margin row on each side: the taps fold and place each v on its own, so
// a row edge may round the other way. Repeat: unwrapped rows; else rows of
// [0, h).
DT_INLINE void rows_of(double lo, double hi, int64_t h, int mode, int64_t* a, int64_t* b) {
  if (mode == MIRROR) {  // the triangle wave's image of [lo, hi] (hi - lo < 2)
    const double s = 2.0 * floor_capped(0.5 * lo), x = lo - s, y = hi - s;  // x in [0, 2), y < 4
    const double fl = fold(x, MIRROR).u, fh = fold(y, MIRROR).u;
    lo = std::min(fl, fh);
    hi = std::max(fl, fh);
    if (x <= 1 && y >= 1) hi = 1;  // a peak inside
    if (x <= 3 && y >= 3) hi = 1;
    if (x <= 2 && y >= 2) lo = 0;  // a trough inside
  }
  const double n = static_cast<double>(h);
  *a = static_cast<int64_t>(floor_capped(lo * n - 0.5)) - 1;
  *b = static_cast<int64_t>(floor_capped(hi * n - 0.5)) + 2;
  if (mode != REPEAT) {
    *a = std::min(std::max<int64_t>(*a, 0), h - 1);
    *b = std::min(std::max<int64_t>(*b, 0), h - 1);
  }
}

// Point e's band key (ScaleBands), or -1 where it writes nothing.
DT_INLINE int32_t tap_key(const ScaleBands& T, const std::vector<Level>& L, double u, double v, const Reads& r,
                          int64_t N, double av, int wrap_v) {
  if (!std::isfinite(u) || !std::isfinite(v)) return -1;
  const double half = N > 1 ? std::abs(av) * (0.5 - 0.5 / static_cast<double>(N)) : 0.0;
  double lo = v - half, hi = v + half;
  if (!std::isfinite(lo) || !std::isfinite(hi)) return static_cast<int32_t>(T.serial);
  if (wrap_v == REPEAT || wrap_v == MIRROR) {
    const double period = wrap_v == REPEAT ? 1.0 : 2.0;
    if (!(hi - lo < period)) return static_cast<int32_t>(T.serial);
    if (wrap_v == REPEAT) {
      const double s = floor_capped(v);
      lo -= s;
      hi -= s;
    }
  }
  int64_t a[2], b[2];
  for (int j = 0; j < r.n; ++j) rows_of(lo, hi, L[r.k[j]].h, wrap_v, &a[j], &b[j]);
  int64_t nb = T.nb0;
  for (int64_t s = 0; s < T.scales; ++s, nb /= 2) {
    int64_t band = std::numeric_limits<int64_t>::max();
    for (int j = 0; j < r.n; ++j) band = std::min(band, floor_div(a[j] * nb, L[r.k[j]].h));
    bool fits = true;
    for (int j = 0; j < r.n; ++j) fits = fits && (b[j] + 1) * nb <= (band + 2) * L[r.k[j]].h;
    if (fits) return static_cast<int32_t>(T.offset[s] + ((band % nb) + nb) % nb);
  }
  return static_cast<int32_t>(T.serial);
}

}  // namespace

std::tuple<std::vector<torch::Tensor>, torch::Tensor, torch::Tensor, torch::Tensor> backward(
    std::vector<torch::Tensor> levels, torch::Tensor uv, torch::Tensor D, torch::Tensor axis, torch::Tensor count,
    torch::Tensor grad, const ReadOptions& opts, const TapNeeds& need) {
  const int64_t wrap_u = opts.wrap_u, wrap_v = opts.wrap_v;
  const double border = opts.border;
  const bool nearest = opts.nearest, d_grad = opts.d_grad;
  const bool need_levels = need.levels, need_uv = need.uv, need_D = need.D;
  bool need_axis = need.axis;
  auto L = shapes(levels, uv, D, axis, count);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(0), M = uv.size(0);
  // Any strides: a channels-last output gradient (nvdiffrast's NHWC) is a
  // [C, M] view with strides (1, C), and transposing it costs more than
  // reading it in place.
  TORCH_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == uv.scalar_type(),
              "mip_read: grad must be [C, M] of uv's dtype");
  const int64_t gsc = grad.stride(0), gsm = grad.stride(1);
  need_axis = need_axis && count.numel();
  std::vector<torch::Tensor> gl(K);
  torch::Tensor guv = need_uv ? torch::zeros({M, 2}, uv.options()) : torch::Tensor();
  torch::Tensor gD = need_D ? torch::zeros({M}, uv.options()) : torch::Tensor();
  torch::Tensor gax = need_axis ? torch::zeros({M, 2}, uv.options()) : torch::Tensor();
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_backward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.data_ptr<scalar_t>());
    Grads<scalar_t> out;
    out.gp.assign(K, nullptr);
    out.uv = need_uv ? guv.data_ptr<scalar_t>() : nullptr;
    out.D = need_D ? gD.data_ptr<scalar_t>() : nullptr;
    out.axis = need_axis ? gax.data_ptr<scalar_t>() : nullptr;
    const int64_t* pc = count.numel() ? count.data_ptr<int64_t>() : nullptr;
    const scalar_t* pa = pc ? axis.data_ptr<scalar_t>() : nullptr;
    const scalar_t *puv = uv.data_ptr<scalar_t>(), *pd = D.data_ptr<scalar_t>(), *pg = grad.data_ptr<scalar_t>();
    std::vector<int32_t> keys;
    ScaleBands bands;
    if (need_levels) {
      // The points' band keys, and the levels read (their gradients are allocated, zeroed, only for those).
      bands = scale_bands(L[0].h);
      const std::vector<char> read = band_keys(M, K, keys, [&](int64_t e, std::vector<char>& rd) {
        const Reads r = reads_of(static_cast<double>(pd[e]), K, nearest, d_grad);
        const int64_t N = tap_count(pc, e);
        const int32_t key = tap_key(bands, L, puv[2 * e], puv[2 * e + 1], r, N,
                                    pc ? static_cast<double>(pa[2 * e + 1]) : 0.0, static_cast<int>(wrap_v));
        if (key >= 0)
          for (int j = 0; j < r.n; ++j) rd[r.k[j]] = 1;
        return key;
      });
      for (int64_t k = 0; k < K; ++k) {
        if (!read[k]) continue;
        gl[k] = torch::zeros_like(levels[k]);
        out.gp[k] = gl[k].template data_ptr<scalar_t>();
      }
    }
    specialized(C, wrap_u, wrap_v, [&](auto cc, auto border_) {
      auto one = [&](int64_t e) {
        backward_point<scalar_t, decltype(cc)::value, decltype(border_)::value>(
            e, C, L, lp, puv, pd, pc, pa, pg, out, gsc, gsm, wrap_u, wrap_v, border, nearest, d_grad);
      };
      if (need_levels) {
        run_banded(keys.data(), M, bands.classes, [&](const int64_t* idx, int64_t n) {
          for (int64_t i = 0; i < n; ++i) one(idx[i]);
        });
      } else {  // no scatter: the points are independent
        at::parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
          for (int64_t e = lo; e < hi; ++e) one(e);
        });
      }
    });
  });
  return {gl, guv, gD, gax};
}

}  // namespace difftex
