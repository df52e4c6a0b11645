// EWA on the CPU (filters/ewa.py _NativeEWA), forward and first-order
// backward, point by point.
//
// The torch ops of filters/ewa.py are its reference (and serve CUDA and
// double backward). Per point the blend of levels floor(D) and floor(D) + 1
// (mip_blend's weights and reads), each the Gaussian-weighted mean of the
// texels inside the padded ellipse as _ewa_level and _pairs compute it, in
// double. Inputs: uv [M, 2] the points with whole periods dropped (finite);
// sigma [M, 3] the scaled J J^T with the minor axis grown; minor [M] that
// axis (scaled); scale [M] the footprint scale; D [M] the clamped level;
// levels [C, h, w].
#include "common.h"
#include "kernels.h"

namespace difftex {
namespace {

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
  const double cap = coarsest ? kMaxMinor : std::max(kMaxMinor, std::max(hk, wk));
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

void ewa_checks(const Tensor& uv, const Tensor& sigma, const Tensor& minor,
                const Tensor& scale) {
  const int64_t M = uv.size(0);
  DT_CHECK(sigma.dim() == 2 && sigma.size(0) == M && sigma.size(1) == 3 && sigma.is_contiguous() &&
                  minor.dim() == 1 && minor.size(0) == M && minor.is_contiguous() && scale.dim() == 1 &&
                  scale.size(0) == M && scale.is_contiguous() && sigma.scalar_type() == uv.scalar_type() &&
                  minor.scalar_type() == uv.scalar_type() && scale.scalar_type() == uv.scalar_type(),
              "mip_read.ewa: sigma [M, 3], minor [M], scale [M] contiguous, of uv's dtype");
}

}  // namespace

// Forward: [C, M]. opts.nearest must be false (EWA blends two levels).
Tensor ewa(std::vector<Tensor> levels, Tensor uv, Tensor sigma, Tensor minor,
                  Tensor scale, Tensor D, int64_t full_h, int64_t full_w, const ReadOptions& opts) {
  DT_CHECK(!opts.nearest, "mip_read.ewa: nearest-mip is not an EWA option");
  const int64_t wrap_u = opts.wrap_u, wrap_v = opts.wrap_v;
  const double border = opts.border;
  const bool d_grad = opts.d_grad;
  auto L = shapes(levels, uv, D, empty({0}, options_of(uv)), empty({0}, options_of(uv).dtype(kInt64)));
  ewa_checks(uv, sigma, minor, scale);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(0), M = uv.size(0);
  auto out = empty({C, M}, options_of(uv));
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_ewa", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.mutable_data_ptr<scalar_t>());
    const scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *ps = sigma.mutable_data_ptr<scalar_t>();
    const scalar_t *pm = minor.mutable_data_ptr<scalar_t>(), *psc = scale.mutable_data_ptr<scalar_t>(), *pd = D.mutable_data_ptr<scalar_t>();
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    parallel_for(0, M, 256, [&](int64_t lo, int64_t hi) {
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
std::tuple<std::vector<Tensor>, Tensor, Tensor, Tensor, Tensor, Tensor>
ewa_backward(std::vector<Tensor> levels, Tensor uv, Tensor sigma, Tensor minor,
             Tensor scale, Tensor D, Tensor grad, int64_t full_h, int64_t full_w,
             const ReadOptions& opts, const EwaNeeds& need) {
  DT_CHECK(!opts.nearest, "mip_read.ewa_backward: nearest-mip is not an EWA option");
  const int64_t wrap_u = opts.wrap_u, wrap_v = opts.wrap_v;
  const double border = opts.border;
  const bool d_grad = opts.d_grad;
  const bool need_levels = need.levels, need_uv = need.uv, need_ellipse = need.ellipse, need_D = need.D;
  auto L = shapes(levels, uv, D, empty({0}, options_of(uv)), empty({0}, options_of(uv).dtype(kInt64)));
  ewa_checks(uv, sigma, minor, scale);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(0), M = uv.size(0);
  grad = contig(grad);
  DT_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == uv.scalar_type(),
              "mip_read.ewa_backward: grad must be [C, M] of uv's dtype");
  std::vector<Tensor> gl(K);
  auto opt = options_of(uv);
  Tensor guv = need_uv ? zeros({M, 2}, opt) : Tensor();
  Tensor gsig = need_ellipse ? zeros({M, 3}, opt) : Tensor();
  Tensor gmin = need_ellipse ? zeros({M}, opt) : Tensor();
  Tensor gsc = need_ellipse ? zeros({M}, opt) : Tensor();
  Tensor gD = need_D ? zeros({M}, opt) : Tensor();
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_ewa_backward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.mutable_data_ptr<scalar_t>());
    const scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *ps = sigma.mutable_data_ptr<scalar_t>();
    const scalar_t *pm = minor.mutable_data_ptr<scalar_t>(), *psc = scale.mutable_data_ptr<scalar_t>(), *pd = D.mutable_data_ptr<scalar_t>();
    const scalar_t* pg = grad.mutable_data_ptr<scalar_t>();
    scalar_t* o_uv = need_uv ? guv.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* o_sig = need_ellipse ? gsig.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* o_min = need_ellipse ? gmin.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* o_sc = need_ellipse ? gsc.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* o_D = need_D ? gD.mutable_data_ptr<scalar_t>() : nullptr;
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
    const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>({static_cast<int64_t>(get_num_threads()),
                                                                    4, M / 4096}));
    std::vector<std::vector<Tensor>> bufs(chunks, std::vector<Tensor>(K));
    std::vector<std::vector<scalar_t*>> ptrs(chunks, std::vector<scalar_t*>(K, nullptr));
    if (need_levels)
      for (int64_t c = 0; c < chunks; ++c)
        for (int64_t k = 0; k < K; ++k)
          if (read[k]) {
            bufs[c][k] = zeros_like(levels[k]);
            ptrs[c][k] = bufs[c][k].template mutable_data_ptr<scalar_t>();
          }
    parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
      for (int64_t c = c0; c < c1; ++c) run(c * M / chunks, (c + 1) * M / chunks, ptrs[c]);
    });
    if (need_levels)
      for (int64_t k = 0; k < K; ++k) {
        if (!read[k]) continue;
        scalar_t* acc = bufs[0][k].template mutable_data_ptr<scalar_t>();
        const int64_t n = bufs[0][k].numel();
        for (int64_t c = 1; c < chunks; ++c) {
          const scalar_t* part = bufs[c][k].template const_data_ptr<scalar_t>();
          for (int64_t i = 0; i < n; ++i) acc[i] += part[i];
        }
        gl[k] = bufs[0][k];
      }
  });
  return {gl, guv, gsig, gmin, gsc, gD};
}

}  // namespace difftex
