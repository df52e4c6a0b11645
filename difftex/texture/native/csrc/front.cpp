// The footprint front end of the bilinear-tap mip filters on the CPU,
// without gradients (texture/taps.py taps).
#include "common.h"
#include "kernels.h"

namespace difftex {
namespace {

// The footprint front end of the bilinear-tap mip filters, without
// gradients (difftex/texture/taps.py taps uses it where no derivative or bias
// needs one): per point, in double, what lod.py's log2_length / footprint
// / ellipse / level and the tap counts of filters/anisotropic.py and
// filters/auto.py give, in one pass instead of 15-50 elementwise torch
// ops. kind 0: trilinear / nearest-mip (the longer footprint vector), 1:
// anisotropic, 2: auto. Returns D [M] clamped to [0, levels - 1] and, for
// kinds 1 and 2, the tap axis [M, 2] in uv (0 for one tap) and the tap
// count [M] (int64). Degenerate footprints as lod.py: NaN or zero
// derivatives are a point (level 0), infinite ones the whole texture (the
// top level), one tap each; a NaN sum with the bias gives level 0.
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

// exp2_bias1: 2^(bias - kLog2Floor) for auto, or -1 for "not yet computed" (a
// per-point bias); inv_h, inv_w: 1 / H, 1 / W; shrink: 1 / (1 + tolerance).
DT_INLINE Taps front_one(double dx0, double dx1, double dy0, double dy1, double bias, double exp2_bias1, double H,
                         double W, double inv_h, double inv_w, int64_t levels, bool is_auto, double cap,
                         double shrink) {
  const double j0 = dx0 * W, j1 = dx1 * H, j2 = dy0 * W, j3 = dy1 * H;
  Taps t{0.0, 0.0, 0.0, 1};
  const double top = std::max(std::max(std::abs(j0), std::abs(j1)), std::max(std::abs(j2), std::abs(j3)));
  // std::max drops a NaN in its second argument, so NaN is tested on its own.
  const bool nan = std::isnan(j0) || std::isnan(j1) || std::isnan(j2) || std::isnan(j3);
  if (nan || !(top > 0) || std::isinf(top)) {
    // A point (zero or NaN derivatives) or the whole texture (infinite
    // ones, NaN winning): one tap at that end of the pyramid.
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
    // auto_tap_count: ratio = 2^(log2 major' - max(log2 minor', LOG2_FLOOR))
    // with x' = x 2^bias, in linear form (exp2_bias1 = 2^(bias - LOG2_FLOOR)); a
    // non-finite bias gives NaN or 0 there, i.e. one tap.
    double m = 1.0;
    if (std::isfinite(bias)) {
      if (exp2_bias1 < 0) exp2_bias1 = std::exp2(bias - kLog2Floor);
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

}  // namespace

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> front(torch::Tensor dx, torch::Tensor dy, torch::Tensor bias,
                                                              double bias0, int64_t H, int64_t W, int64_t levels,
                                                              int64_t kind, double max_aniso, double tolerance) {
  const int64_t M = dx.size(0);
  // Any strides: nvdiffrast's uv_da interleaves uv_dx and uv_dy, and a copy
  // of each would cost more than this pass.
  TORCH_CHECK(dx.dim() == 2 && dx.size(1) == 2 && dx.device().is_cpu() && dy.sizes() == dx.sizes() &&
                  dy.scalar_type() == dx.scalar_type(),
              "mip_read.front: uv_dx, uv_dy must be CPU [M, 2] of one dtype");
  TORCH_CHECK(bias.numel() == 0 || (bias.dim() == 1 && bias.size(0) == M && bias.is_contiguous() &&
                                    bias.scalar_type() == dx.scalar_type()),
              "mip_read.front: bias must be contiguous [M] of uv_dx's dtype, or empty");
  TORCH_CHECK(levels >= 1 && kind >= 0 && kind <= 2, "mip_read.front: levels >= 1, kind 0, 1 or 2");
  const bool is_auto = kind == 2;
  const double cap = std::max(std::floor(max_aniso), 1.0), exp2_bias0 = std::exp2(bias0 - kLog2Floor);
  const double shrink = 1.0 / (1.0 + tolerance);
  auto D = torch::empty({M}, dx.options());
  auto axis = torch::empty({kind ? M : 0, 2}, dx.options());
  auto count = torch::empty({kind ? M : 0}, dx.options().dtype(torch::kInt64));
  AT_DISPATCH_FLOATING_TYPES(dx.scalar_type(), "mip_read_front", [&] {
    const scalar_t* px = dx.data_ptr<scalar_t>();
    const scalar_t* py = dy.data_ptr<scalar_t>();
    const int64_t xr = dx.stride(0), xc = dx.stride(1), yr = dy.stride(0), yc = dy.stride(1);
    const scalar_t* pb = bias.numel() ? bias.data_ptr<scalar_t>() : nullptr;
    scalar_t* pD = D.data_ptr<scalar_t>();
    scalar_t* pa = axis.data_ptr<scalar_t>();
    int64_t* pn = count.data_ptr<int64_t>();
    const double h = static_cast<double>(H), w = static_cast<double>(W);
    at::parallel_for(0, M, 2048, [&](int64_t lo, int64_t hi) {
      for (int64_t e = lo; e < hi; ++e) {
        const double b = pb ? static_cast<double>(pb[e]) : bias0;
        const double dx0 = px[xr * e], dx1 = px[xr * e + xc], dy0 = py[yr * e], dy1 = py[yr * e + yc];
        if (kind == 0) {
          pD[e] = static_cast<scalar_t>(trilinear_level(dx0, dx1, dy0, dy1, b, h, w, levels));
          continue;
        }
        Taps t = front_one(dx0, dx1, dy0, dy1, b, pb ? -1.0 : exp2_bias0, h, w, 1.0 / h, 1.0 / w, levels, is_auto,
                           cap, shrink);
        pD[e] = static_cast<scalar_t>(t.D);
        pa[2 * e] = static_cast<scalar_t>(t.ax);
        pa[2 * e + 1] = static_cast<scalar_t>(t.ay);
        pn[e] = t.n;
      }
    });
  });
  return {D, axis, count};
}

}  // namespace difftex
