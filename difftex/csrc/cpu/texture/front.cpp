// The footprint front end of the bilinear-tap mip filters on the CPU,
// without gradients (texture/taps.py taps).
#include "common.h"
#include "kernels.h"

#if DT_HAVE_AVX2
#include <immintrin.h>
#endif

namespace difftex {
namespace {

// The footprint front end of the bilinear-tap mip filters, without
// gradients (difftex/texture/taps.py taps uses it where no derivative or bias
// needs one): per point, in double, what lod.py's log2_length / footprint
// / ellipse / level and the tap counts of filters/anisotropic.py and
// filters/auto.py give, in one pass instead of 15-50 elementwise torch
// ops. kind 0: trilinear / nearest-mip (the longer footprint vector), 1:
// anisotropic, 2: auto. Returns D [M] clamped to [0, levels - 1] and, for
// kinds 1 and 2, the tap axis [M, 2] in uv (the major axis, 0 for a degenerate footprint) and the tap
// count [M] (int64). Degenerate footprints as lod.py: NaN or zero
// derivatives are a point (level 0), infinite ones the whole texture (the
// top level), one tap each; a NaN sum with the bias gives level 0.
//
// float32 derivatives whose two components are adjacent (any row stride:
// nvdiffrast's uv_da too) go four points at a time where the CPU has AVX2
// (front_range4, on where set_simd is): the scalar loop's operations lane by
// lane but for its own log2. At 512^2 points, 2 threads: trilinear 0.47 ms
// against 1.30 for the scalar loop, anisotropic 1.22 against 3.13, auto
// 1.63 against 3.36 (the torch path: 2.2-3.6, 10-18, 12-18 ms).
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

#if DT_HAVE_AVX2
// log2 of four positive, finite, normal doubles, within 1e-12: x = 2^e m with m in [sqrt(1/2), sqrt(2)),
// log2 m = 2 atanh(s) / ln 2 with s = (m - 1) / (m + 1), |s| < 0.1716, by the series of atanh to s^13 (the
// rest is below 1e-12 of log2 m: float32 levels round as from the exact value).
DT_AVX2 __m256d log2_4(__m256d x) {
  const __m256i bits = _mm256_castpd_si256(x);
  const __m256d one = _mm256_set1_pd(1.0);
  const __m256i mantissa = _mm256_and_si256(bits, _mm256_set1_epi64x(0x000FFFFFFFFFFFFFLL));
  __m256d m = _mm256_castsi256_pd(_mm256_or_si256(mantissa, _mm256_castpd_si256(one)));  // in [1, 2)
  // The biased exponents (positive x: no sign bit) sit in the low 32 bits of each lane.
  const __m256i ex = _mm256_srli_epi64(bits, 52);
  const __m256i low = _mm256_permutevar8x32_epi32(ex, _mm256_setr_epi32(0, 2, 4, 6, 0, 0, 0, 0));
  const __m128i e32 = _mm256_castsi256_si128(low);
  __m256d e = _mm256_sub_pd(_mm256_cvtepi32_pd(e32), _mm256_set1_pd(1023.0));
  const __m256d big = _mm256_cmp_pd(m, _mm256_set1_pd(1.4142135623730951), _CMP_GT_OQ);
  m = _mm256_blendv_pd(m, _mm256_mul_pd(m, _mm256_set1_pd(0.5)), big);
  e = _mm256_add_pd(e, _mm256_and_pd(big, one));
  const __m256d s = _mm256_div_pd(_mm256_sub_pd(m, one), _mm256_add_pd(m, one)), s2 = _mm256_mul_pd(s, s);
  // 1 + s2 / 3 + ... + s2^6 / 13 in Estrin's scheme: a shorter dependency chain than Horner's (measured: the
  // trilinear loop 7% faster)
  const auto c = [](double k) __attribute__((target("avx2,fma"))) { return _mm256_set1_pd(1.0 / k); };
  const auto lin = [&](double a, double b) __attribute__((target("avx2,fma"))) {
    return _mm256_add_pd(c(a), _mm256_mul_pd(c(b), s2));
  };
  const __m256d s4 = _mm256_mul_pd(s2, s2), s8 = _mm256_mul_pd(s4, s4);
  const __m256d p = _mm256_add_pd(_mm256_add_pd(lin(1, 3), _mm256_mul_pd(lin(5, 7), s4)),
                                  _mm256_mul_pd(s8, _mm256_add_pd(lin(9, 11), _mm256_mul_pd(c(13), s4))));
  return _mm256_add_pd(e, _mm256_mul_pd(_mm256_mul_pd(s, p), _mm256_set1_pd(2.0 / 0.6931471805599453)));
}

// Two float32 uv pairs (points at p and p + stride) as four doubles (u0, v0, u1, v1).
DT_AVX2 __m256d pairs2(const float* p, int64_t stride) {
  if (stride == 2) return _mm256_cvtps_pd(_mm_loadu_ps(p));
  const __m128i a = _mm_loadl_epi64(reinterpret_cast<const __m128i*>(p));
  const __m128i b = _mm_loadl_epi64(reinterpret_cast<const __m128i*>(p + stride));
  return _mm256_cvtps_pd(_mm_castsi128_ps(_mm_unpacklo_epi64(a, b)));
}

// front's arguments, and as vectors for the vector front end.
struct FrontArgs {
  double W, H, top, cap, shrink, exp2_bias0, bias0;
  int kind;
};
struct Front4 {
  __m256d W, H, inv_w, inv_h, top, cap, shrink, exp2_bias0;
  double bias0;
  int kind;  // as front's
};

// Four points' derivative components from pairs2 halves lo = (x0, y0, x1, y1), hi = (x2, y2, x3, y3).
DT_AVX2 void split4(__m256d lo, __m256d hi, __m256d* x, __m256d* y) {
  *x = _mm256_permute4x64_pd(_mm256_unpacklo_pd(lo, hi), 0xD8);
  *y = _mm256_permute4x64_pd(_mm256_unpackhi_pd(lo, hi), 0xD8);
}

// std::min(a, b) and std::max(a, b) lane by lane, NaN cases included (min_pd / max_pd return their second
// operand where either is NaN; std::min / std::max their first).
DT_AVX2 __m256d min4(__m256d a, __m256d b) { return _mm256_min_pd(b, a); }
DT_AVX2 __m256d max4(__m256d a, __m256d b) { return _mm256_max_pd(b, a); }

// clamp_level: NaN to 0, then into [0, levels - 1].
DT_AVX2 __m256d clamp_level4(__m256d x, __m256d top) {
  return _mm256_min_pd(_mm256_max_pd(x, _mm256_setzero_pd()), top);
}

// Four points' derivative components (float32 at px, py, row strides xr, yr) and biases (at pb, or bias0
// where null), as doubles.
DT_AVX2 __m256d load4(const float* px, int64_t xr, const float* py, int64_t yr, const float* pb, const Front4& f,
                      __m256d* dx0, __m256d* dx1, __m256d* dy0, __m256d* dy1) {
  split4(pairs2(px, xr), pairs2(px + 2 * xr, xr), dx0, dx1);
  split4(pairs2(py, yr), pairs2(py + 2 * yr, yr), dy0, dy1);
  return pb ? _mm256_cvtps_pd(_mm_loadu_ps(pb)) : _mm256_set1_pd(f.bias0);
}

// trilinear_level of four points (float32 derivatives at px, py; biases at pb, or bias0 where null).
DT_AVX2 void trilinear_level4(const float* px, int64_t xr, const float* py, int64_t yr, const float* pb,
                              const Front4& f, float* pD) {
  const __m256d zero = _mm256_setzero_pd(), far = _mm256_set1_pd(kFar);
  __m256d dx0, dx1, dy0, dy1;
  const __m256d b = load4(px, xr, py, yr, pb, f, &dx0, &dx1, &dy0, &dy1);
  const auto len2 = [&](__m256d x, __m256d y) __attribute__((target("avx2,fma"))) {
    x = _mm256_mul_pd(x, f.W);
    y = _mm256_mul_pd(y, f.H);
    return _mm256_add_pd(_mm256_mul_pd(x, x), _mm256_mul_pd(y, y));
  };
  const __m256d p2 = len2(dx0, dx1), q2 = len2(dy0, dy1);
  // NaN in either: level 0 (-kFar); else the longer; 0: -kFar; infinite: +kFar
  const __m256d nan = _mm256_cmp_pd(p2, q2, _CMP_UNORD_Q), longer = _mm256_max_pd(p2, q2);
  const __m256d small = _mm256_or_pd(nan, _mm256_cmp_pd(longer, zero, _CMP_EQ_OQ));
  const __m256d inf = _mm256_set1_pd(std::numeric_limits<double>::infinity());
  const __m256d large = _mm256_andnot_pd(nan, _mm256_cmp_pd(longer, inf, _CMP_EQ_OQ));  // NaN wins over inf
  __m256d v = _mm256_mul_pd(_mm256_set1_pd(0.5),
                            log2_4(_mm256_blendv_pd(longer, _mm256_set1_pd(1.0), _mm256_or_pd(small, large))));
  v = _mm256_blendv_pd(_mm256_blendv_pd(v, _mm256_sub_pd(zero, far), small), far, large);
  _mm_storeu_ps(pD, _mm256_cvtpd_ps(clamp_level4(_mm256_add_pd(v, b), f.top)));
}

// front_one of four points (float32 derivatives at px, py; biases at pb, or bias0 where null), its
// operations lane by lane: the count and axis have the scalar loop's bits, the level its value to float32
// rounding (log2_4).
DT_AVX2 void front_taps4(const float* px, int64_t xr, const float* py, int64_t yr, const float* pb,
                         const Front4& f, float* pD, float* pa, int64_t* pn) {
  const __m256d zero = _mm256_setzero_pd(), one = _mm256_set1_pd(1.0), half = _mm256_set1_pd(0.5);
  const __m256d sign = _mm256_set1_pd(-0.0), tol = _mm256_set1_pd(kRatioTol);
  const auto abs4 = [&](__m256d x) __attribute__((target("avx2,fma"))) { return _mm256_andnot_pd(sign, x); };
  const auto mul = [](__m256d a, __m256d b) __attribute__((target("avx2,fma"))) { return _mm256_mul_pd(a, b); };
  const auto add = [](__m256d a, __m256d b) __attribute__((target("avx2,fma"))) { return _mm256_add_pd(a, b); };
  const auto sub = [](__m256d a, __m256d b) __attribute__((target("avx2,fma"))) { return _mm256_sub_pd(a, b); };
  // -floor_capped(kRatioTol - x) (the capping only matters past 2^51, where the count is capped anyway)
  const auto ceil_tol = [&](__m256d x) __attribute__((target("avx2,fma"))) {
    return sub(zero, _mm256_floor_pd(sub(tol, x)));
  };
  __m256d dx0, dx1, dy0, dy1;
  const __m256d bias = load4(px, xr, py, yr, pb, f, &dx0, &dx1, &dy0, &dy1);
  const __m256d j0 = mul(dx0, f.W), j1 = mul(dx1, f.H), j2 = mul(dy0, f.W), j3 = mul(dy1, f.H);
  const __m256d top = max4(max4(abs4(j0), abs4(j1)), max4(abs4(j2), abs4(j3)));
  const __m256d nan = _mm256_or_pd(_mm256_cmp_pd(j0, j1, _CMP_UNORD_Q), _mm256_cmp_pd(j2, j3, _CMP_UNORD_Q));
  const __m256d inf = _mm256_cmp_pd(top, _mm256_set1_pd(std::numeric_limits<double>::infinity()), _CMP_EQ_OQ);
  const __m256d odd = _mm256_or_pd(_mm256_or_pd(nan, inf), _mm256_cmp_pd(top, zero, _CMP_NGT_UQ));
  // the degenerate lanes: a point or the whole texture, one tap (the rest runs on top = 1 there)
  const __m256d far = _mm256_blendv_pd(_mm256_set1_pd(-kFar), _mm256_set1_pd(kFar), _mm256_andnot_pd(nan, inf));
  const __m256d D_odd = clamp_level4(add(far, bias), f.top);
  const __m256d t = _mm256_blendv_pd(top, one, odd);
  const __m256d r = _mm256_div_pd(one, t), p0 = mul(j0, r), p1 = mul(j1, r), q0 = mul(j2, r), q1 = mul(j3, r);
  const __m256d a = add(mul(p0, p0), mul(q0, q0)), c = add(mul(p1, p1), mul(q1, q1));
  const __m256d b = add(mul(p0, p1), mul(q0, q1)), hd = mul(half, sub(a, c));
  const __m256d disc = _mm256_sqrt_pd(add(mul(hd, hd), mul(b, b))), lam = add(mul(half, add(a, c)), disc);
  const __m256d major = _mm256_sqrt_pd(lam), det = abs4(sub(mul(p0, q1), mul(q0, p1)));
  const __m256d q = _mm256_blendv_pd(f.cap, max4(_mm256_div_pd(lam, det), one),
                                     _mm256_cmp_pd(det, zero, _CMP_GT_OQ));
  __m256d n = min4(max4(ceil_tol(q), one), f.cap);
  const __m256d extent = mul(major, t);  // major * top
  if (f.kind == 2) {
    // auto_tap_count (front_one), where the bias is finite; one tap elsewhere
    const __m256d finite = _mm256_cmp_pd(abs4(bias), _mm256_set1_pd(std::numeric_limits<double>::infinity()),
                                         _CMP_LT_OQ);
    __m256d e1 = f.exp2_bias0;
    if (pb) {
      alignas(32) double bb[4], ee[4];
      _mm256_store_pd(bb, bias);
      for (int j = 0; j < 4; ++j) ee[j] = std::exp2(bb[j] - kLog2Floor);
      e1 = _mm256_load_pd(ee);
    }
    const __m256d minor = min4(_mm256_div_pd(det, major), major);
    const __m256d ratio = _mm256_blendv_pd(mul(extent, e1), q,
                                           _mm256_cmp_pd(mul(mul(minor, t), e1), one, _CMP_GE_OQ));
    const __m256d full = min4(ceil_tol(min4(ratio, _mm256_set1_pd(kMaxRatio))), f.cap);
    __m256d m = _mm256_blendv_pd(ceil_tol(mul(full, f.shrink)), full, _mm256_cmp_pd(ratio, f.cap, _CMP_GT_OQ));
    m = _mm256_blendv_pd(one, min4(max4(m, one), f.cap), finite);
    n = _mm256_blendv_pd(n, min4(n, m), _mm256_cmp_pd(n, one, _CMP_GT_OQ));
  }
  n = _mm256_blendv_pd(n, one, odd);
  const __m256d D = clamp_level4(add(log2_4(_mm256_div_pd(extent, n)), bias), f.top);
  _mm_storeu_ps(pD, _mm256_cvtpd_ps(_mm256_blendv_pd(D, D_odd, odd)));
  // the major axis as a uv vector (front_one), 0 in the degenerate lanes
  const __m256d ac = _mm256_cmp_pd(a, c, _CMP_GE_OQ);
  __m256d ex = _mm256_blendv_pd(b, sub(lam, c), ac);
  const __m256d ey = _mm256_blendv_pd(sub(lam, a), b, ac);
  const __m256d round = _mm256_cmp_pd(add(mul(ex, ex), mul(ey, ey)), zero, _CMP_EQ_OQ);
  ex = _mm256_blendv_pd(ex, one, round);
  const __m256d signed_extent = _mm256_blendv_pd(extent, sub(zero, extent), _mm256_cmp_pd(ex, zero, _CMP_LT_OQ));
  const __m256d s = _mm256_div_pd(signed_extent, _mm256_sqrt_pd(add(mul(ex, ex), mul(ey, ey))));
  const __m128 ax = _mm256_cvtpd_ps(_mm256_andnot_pd(odd, mul(mul(ex, s), f.inv_w)));
  const __m128 ay = _mm256_cvtpd_ps(_mm256_andnot_pd(odd, mul(mul(ey, s), f.inv_h)));
  _mm_storeu_ps(pa, _mm_unpacklo_ps(ax, ay));
  _mm_storeu_ps(pa + 4, _mm_unpackhi_ps(ax, ay));
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(pn), _mm256_cvtepi32_epi64(_mm256_cvttpd_epi32(n)));
}

// front for the points [lo, hi) of float32 derivatives whose two components are adjacent (any row stride),
// four at a time, the last (up to three) points through a copy: every point takes this path, so the
// results do not depend on how the threads split the points. The scalar loop's operations lane by lane, but
// for log2 (within 1e-12): the same counts and axes, the levels to float32 rounding (the tests compare).
__attribute__((target("avx2,fma"))) void front_range4(int64_t lo, int64_t hi, const float* px, int64_t xr,
                                                      const float* py, int64_t yr, const float* pb,
                                                      const FrontArgs& g, float* pD, float* pa, int64_t* pn) {
  const Front4 f{_mm256_set1_pd(g.W), _mm256_set1_pd(g.H), _mm256_set1_pd(1.0 / g.W), _mm256_set1_pd(1.0 / g.H),
                 _mm256_set1_pd(g.top), _mm256_set1_pd(g.cap), _mm256_set1_pd(g.shrink), _mm256_set1_pd(g.exp2_bias0),
                 g.bias0, g.kind};
  const auto four = [&](const float* x, int64_t sx, const float* y, int64_t sy, const float* b, float* d, float* a,
                        int64_t* n) __attribute__((target("avx2,fma"))) {
    if (f.kind == 0)
      trilinear_level4(x, sx, y, sy, b, f, d);
    else
      front_taps4(x, sx, y, sy, b, f, d, a, n);
  };
  int64_t e = lo;
  for (; e + 4 <= hi; e += 4)
    four(px + xr * e, xr, py + yr * e, yr, pb ? pb + e : nullptr, pD + e, f.kind ? pa + 2 * e : nullptr,
         f.kind ? pn + e : nullptr);
  if (e == hi) return;
  float x[8] = {}, y[8] = {}, b[4] = {}, d[4], a[8];
  int64_t n[4];
  for (int64_t j = 0; j < hi - e; ++j) {
    x[2 * j] = px[xr * (e + j)], x[2 * j + 1] = px[xr * (e + j) + 1];
    y[2 * j] = py[yr * (e + j)], y[2 * j + 1] = py[yr * (e + j) + 1];
    if (pb) b[j] = pb[e + j];
  }
  four(x, 2, y, 2, pb ? b : nullptr, d, a, n);
  for (int64_t j = 0; j < hi - e; ++j) {
    pD[e + j] = d[j];
    if (f.kind) pa[2 * (e + j)] = a[2 * j], pa[2 * (e + j) + 1] = a[2 * j + 1], pn[e + j] = n[j];
  }
}
#endif

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
  // The major axis as a uv vector, also for one tap (the cube map raises a point's count near an edge to its
  // neighbouring face's and spreads the taps along its own axis): the eigenvector of J J^T = [a b; b c] for
  // lam, oriented as lod.py's angle 0.5 atan2(2b, a - c) (x >= 0), which is 0 for a round footprint.
  double ex = a >= c ? lam - c : b, ey = a >= c ? b : lam - a;
  if (ex * ex + ey * ey == 0) ex = 1;
  const double s = (ex < 0 ? -major * top : major * top) / std::sqrt(ex * ex + ey * ey);
  t.ax = ex * s * inv_w;
  t.ay = ey * s * inv_h;
  return t;
}

}  // namespace

std::tuple<Tensor, Tensor, Tensor> front(Tensor dx, Tensor dy, Tensor bias,
                                                              double bias0, int64_t H, int64_t W, int64_t levels,
                                                              int64_t kind, double max_aniso, double tolerance) {
  const int64_t M = dx.size(0);
  // Any strides: nvdiffrast's uv_da interleaves uv_dx and uv_dy, and a copy
  // of each would cost more than this pass.
  DT_CHECK(dx.dim() == 2 && dx.size(1) == 2 && dx.is_cpu() && dy.sizes() == dx.sizes() &&
                  dy.scalar_type() == dx.scalar_type(),
              "mip_read.front: uv_dx, uv_dy must be CPU [M, 2] of one dtype");
  DT_CHECK(bias.numel() == 0 || (bias.dim() == 1 && bias.size(0) == M && bias.is_contiguous() &&
                                    bias.scalar_type() == dx.scalar_type()),
              "mip_read.front: bias must be contiguous [M] of uv_dx's dtype, or empty");
  DT_CHECK(levels >= 1 && kind >= 0 && kind <= 2, "mip_read.front: levels >= 1, kind 0, 1 or 2");
  const bool is_auto = kind == 2;
  const double cap = std::max(std::floor(max_aniso), 1.0), exp2_bias0 = std::exp2(bias0 - kLog2Floor);
  const double shrink = 1.0 / (1.0 + tolerance);
  auto D = empty({M}, options_of(dx));
  auto axis = empty({kind ? M : 0, 2}, options_of(dx));
  auto count = empty({kind ? M : 0}, options_of(dx).dtype(kInt64));
  DT_DISPATCH_FLOATING_TYPES(dx.scalar_type(), "mip_read_front", [&] {
    const scalar_t* px = dx.mutable_data_ptr<scalar_t>();
    const scalar_t* py = dy.mutable_data_ptr<scalar_t>();
    const int64_t xr = dx.stride(0), xc = dx.stride(1), yr = dy.stride(0), yc = dy.stride(1);
    const scalar_t* pb = bias.numel() ? bias.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* pD = D.mutable_data_ptr<scalar_t>();
    scalar_t* pa = axis.mutable_data_ptr<scalar_t>();
    int64_t* pn = count.mutable_data_ptr<int64_t>();
    const double h = static_cast<double>(H), w = static_cast<double>(W);
    parallel_for(0, M, 2048, [&](int64_t lo, int64_t hi) {
#if DT_HAVE_AVX2
      // (a run-time dtype test: the dispatch's lambda is no template, so both dtypes compile this)
      if (std::is_same_v<scalar_t, float> && xc == 1 && yc == 1 && simd_on()) {
        const FrontArgs f{w, h, static_cast<double>(levels - 1), cap, shrink, exp2_bias0, bias0,
                          static_cast<int>(kind)};
        return front_range4(lo, hi, reinterpret_cast<const float*>(px), xr, reinterpret_cast<const float*>(py), yr,
                            reinterpret_cast<const float*>(pb), f, reinterpret_cast<float*>(pD),
                            reinterpret_cast<float*>(pa), pn);
      }
#endif
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
