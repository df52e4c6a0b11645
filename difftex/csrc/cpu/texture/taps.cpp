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

#if DT_HAVE_AVX2
#include <immintrin.h>
#endif

namespace difftex {

std::vector<Level> shapes(const std::vector<Tensor>& levels, const Tensor& uv, const Tensor& D,
                          const Tensor& axis, const Tensor& count) {
  DT_CHECK(!levels.empty(), "mip_read: no levels");
  const int64_t M = uv.size(0);
  DT_CHECK(uv.dim() == 2 && uv.size(1) == 2 && uv.is_contiguous(), "mip_read: uv must be contiguous [M, 2]");
  DT_CHECK(D.dim() == 1 && D.size(0) == M && D.scalar_type() == uv.scalar_type() && D.is_contiguous(),
              "mip_read: D must be contiguous [M] of uv's dtype");
  DT_CHECK(count.numel() == 0 || (count.dim() == 1 && count.size(0) == M && count.is_contiguous() &&
                                     count.scalar_type() == kInt64 && axis.sizes() == uv.sizes() &&
                                     axis.is_contiguous() && axis.scalar_type() == uv.scalar_type()),
              "mip_read: count must be contiguous int64 [M] and axis contiguous [M, 2] (or both empty)");
  std::vector<Level> out;
  int64_t C = levels[0].size(0);
  for (const auto& t : levels) {
    DT_CHECK(t.dim() == 3 && t.size(0) == C && t.is_contiguous() && t.scalar_type() == uv.scalar_type() &&
                    t.is_cpu(), "mip_read: levels must be contiguous CPU [C, h, w] of uv's dtype");
    out.push_back({t.size(1), t.size(2), t.size(1) * t.size(2)});
  }
  return out;
}


namespace {

// Taps of point e: N = count[e] (1 without counts) at uv + o_i * axis,
// o_i = (i + 1/2) / N - 1/2, each weighted 1 / N (filters/anisotropic.py).
inline int64_t tap_count(const int64_t* pc, int64_t e) { return pc == nullptr ? 1 : (pc[e] < 1 ? 1 : pc[e]); }
inline double tap_offset(int64_t i, int64_t N) { return (static_cast<double>(i) + 0.5) / static_cast<double>(N) - 0.5; }

// One stochastic trilinear draw of point e (ReadOptions::stochastic; filters/stochastic.py is the
// reference): the level, floor(D) + 1 with probability p = 3/4 frac(D) + 1/8 where D blends two levels
// (else floor(D) alone), in r as one read of weight 1; and the drawn level's weight in the blend over its
// probability, w / p (scalar_t, rounded as the torch path rounds it), with its d / dD, +-1 / p. frac, p and
// w are computed in the texture's dtype as the torch path does, so that a float32 D draws the level it draws.
template <typename scalar_t>
struct Draw {
  Reads r;
  scalar_t scale;
  double dscale;
};

template <typename scalar_t>
DT_INLINE Draw<scalar_t> draw_of(const ReadOptions& o, int64_t e, scalar_t d, int64_t K) {
  Draw<scalar_t> dr;
  const scalar_t k0 = static_cast<scalar_t>(floor_capped(static_cast<double>(d)));
  const scalar_t f = d - k0;
  const scalar_t p = f > 0 ? static_cast<scalar_t>(0.75) * f + static_cast<scalar_t>(0.125) : scalar_t(0);
  // upper is a coin toss: the choices below are table lookups, not branches (measured: the mispredicted
  // branches took as long as the reads).
  const int upper = stratified_uniform(o.seed, static_cast<uint64_t>(o.first + e), o.strata) < static_cast<double>(p);
  int64_t k = static_cast<int64_t>(k0) + upper;
  k = k < 0 ? 0 : (k > K - 1 ? K - 1 : k);
  dr.r.n = 1;
  dr.r.k[0] = k;
  dr.r.wt[0] = 1.0;
  dr.r.dwt[0] = 0.0;
  const scalar_t pdf_of[2] = {scalar_t(1) - p, p}, w_of[2] = {scalar_t(1) - f, f};
  const double sign[2] = {-1.0, 1.0};
  const scalar_t pdf = pdf_of[upper];
  // An integer level (f = 0) is read alone: weight 1, no level derivative (stochastic.py's docstring).
  const bool blend = f > 0;
  dr.scale = blend ? w_of[upper] / pdf : scalar_t(1);
  dr.dscale = blend ? sign[upper] / static_cast<double>(pdf) : 0.0;
  return dr;
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


// A stochastic draw of one point, placed: its level, the tap's texels on it, w / p and d(w / p) / dD; live
// is false for a non-finite uv (NaN, no gradient).
template <typename scalar_t>
struct Placed {
  Bilinear b;
  int64_t k;
  scalar_t scale;
  double dscale;
  bool live;
};

template <typename scalar_t>
DT_INLINE void place_draw(const ReadOptions& o, int64_t e, const std::vector<Level>& L, const scalar_t* puv,
                          const scalar_t* pd, int64_t wrap_u, int64_t wrap_v, Placed<scalar_t>& q) {
  const double u = puv[2 * e], v = puv[2 * e + 1];
  q.live = std::isfinite(u) && std::isfinite(v);
  if (!q.live) return;
  const Draw<scalar_t> dr = draw_of<scalar_t>(o, e, pd[e], static_cast<int64_t>(L.size()));
  q.k = dr.r.k[0];
  q.scale = dr.scale;
  q.dscale = dr.dscale;
  const Level& lv = L[q.k];
  q.b = taps_folded(fold(u, wrap_u), fold(v, wrap_v), lv.h, lv.w, wrap_u, wrap_v);
}

// The drawn levels are a coin toss per point, so the lines a point reads are seldom those its neighbour just
// read: the points are placed a block ahead (kDrawBlock) and their rows prefetched (both rows of the tap, every
// channel plane), so that the misses of a block overlap the reads of the one before (as prepare_taps8 does
// for the deterministic taps).
constexpr int kDrawBlock = 16;

template <typename scalar_t>
DT_INLINE void prefetch_draw(const Placed<scalar_t>& q, int64_t C, const std::vector<Level>& L,
                             const std::vector<const scalar_t*>& lp, scalar_t* const* gp) {
  if (!q.live) return;
  const int64_t plane = L[q.k].plane;
  for (int64_t c = 0; c < C; ++c) {
    DT_PREFETCH(lp[q.k] + c * plane + q.b.idx[0], false);
    DT_PREFETCH(lp[q.k] + c * plane + q.b.idx[2], false);
    if (gp != nullptr && gp[q.k] != nullptr) {
      DT_PREFETCH(gp[q.k] + c * plane + q.b.idx[0], true);
      DT_PREFETCH(gp[q.k] + c * plane + q.b.idx[2], true);
    }
  }
}

// The stochastic forward of points [lo, hi): forward_range's arithmetic for one tap of weight 1, then times
// w / p (the same bits as forward_range with a ReadOptions), by blocks placed one ahead.
template <typename scalar_t, int CC, bool kBorder>
void forward_draws(int64_t lo, int64_t hi, int64_t Cdyn, const std::vector<Level>& L,
                   const std::vector<const scalar_t*>& lp, const scalar_t* puv, const scalar_t* pd, scalar_t* po,
                   int64_t M, int64_t wrap_u, int64_t wrap_v, double border, const ReadOptions& o) {
  const int64_t C = CC > 0 ? CC : Cdyn;
  const scalar_t bv = static_cast<scalar_t>(border);
  Placed<scalar_t> blk[2][kDrawBlock];
  auto fill = [&](int64_t e0, Placed<scalar_t>* q) {
    const int64_t n = std::min<int64_t>(kDrawBlock, hi - e0);
    for (int64_t i = 0; i < n; ++i) {
      place_draw(o, e0 + i, L, puv, pd, wrap_u, wrap_v, q[i]);
      prefetch_draw<scalar_t>(q[i], C, L, lp, nullptr);
    }
    return n;
  };
  int cur = 0;
  int64_t n = lo < hi ? fill(lo, blk[0]) : 0;
  for (int64_t e0 = lo; n > 0; e0 += kDrawBlock, cur ^= 1) {
    const int64_t m = e0 + kDrawBlock < hi ? fill(e0 + kDrawBlock, blk[cur ^ 1]) : 0;
    for (int64_t i = 0; i < n; ++i) {
      const Placed<scalar_t>& q = blk[cur][i];
      const int64_t e = e0 + i;
      if (!q.live) {
        for (int64_t c = 0; c < C; ++c) po[c * M + e] = std::numeric_limits<scalar_t>::quiet_NaN();
        continue;
      }
      const Bilinear& b = q.b;
      const Level& lv = L[q.k];
      const double wl = 1.0;
      const scalar_t wts[4] = {static_cast<scalar_t>(wl * (1 - b.fx) * (1 - b.fy)), static_cast<scalar_t>(wl * b.fx * (1 - b.fy)),
                               static_cast<scalar_t>(wl * (1 - b.fx) * b.fy), static_cast<scalar_t>(wl * b.fx * b.fy)};
      const scalar_t* p = lp[q.k];
      for (int64_t c = 0; c < C; ++c) {
        const scalar_t* pp = p + c * lv.plane;
        scalar_t s = 0;
        for (int r = 0; r < 4; ++r) s += wts[r] * (!kBorder || b.inside[r] ? pp[b.idx[r]] : bv);
        scalar_t acc = 0.0;
        acc += s;
        po[c * M + e] = acc * q.scale;
      }
    }
    n = m;
  }
}

// ---------------------------------------------------------------------------
// One tap a point (trilinear, nearest-mip) in float32, eight points at a
// time (AVX2, checked at run time as single.cpp does): a group of eight
// whose points read the same levels (nearly every group: the level follows
// the footprint, which changes slowly over an image) computes its taps in
// vector registers and reads each tap's texels of the eight points in one
// gather; the other groups, and every point with a non-finite coordinate,
// go through the scalar loop. The coordinates are common.h's fold and
// place in double (the same texels and fractions as the scalar loop, bit
// for bit), the texel arithmetic is the scalar loop's float32 arithmetic
// in the same order: a point gives the same bits on either path, so how
// points fall into groups (the thread count) changes nothing.
// ---------------------------------------------------------------------------
#if DT_HAVE_AVX2

// Eight points' bilinear taps along one axis of n texels (common.h fold + place): the two wrapped indices,
// whether each is a texel (border), the fraction and the fold slope, each as two halves of four doubles where
// double.
struct Place8 {
  __m256i i0, i1, in0, in1;
  __m256d f[2], slope[2];
};

DT_AVX2 __m256d frac4(__m256d x) {  // common.h frac: 0 from 2^52 on
  const __m256d f = _mm256_sub_pd(x, _mm256_floor_pd(x));
  const __m256d small = _mm256_cmp_pd(_mm256_andnot_pd(_mm256_set1_pd(-0.0), x), _mm256_set1_pd(kTwo52), _CMP_LT_OQ);
  return _mm256_and_pd(f, small);
}

DT_AVX2 void place8(const double* u, int32_t n, int mode, Place8& a) {
  const __m256d one = _mm256_set1_pd(1.0), nd = _mm256_set1_pd(static_cast<double>(n));
  __m128i lo[2];
  for (int h = 0; h < 2; ++h) {
    __m256d x = _mm256_loadu_pd(u + 4 * h);
    a.slope[h] = one;
    if (mode == REPEAT) {
      x = frac4(x);
    } else if (mode == MIRROR) {
      const __m256d f = frac4(_mm256_mul_pd(_mm256_set1_pd(0.5), x));
      const __m256d s = _mm256_sub_pd(_mm256_add_pd(f, f), one);
      x = _mm256_sub_pd(one, _mm256_andnot_pd(_mm256_set1_pd(-0.0), s));
      a.slope[h] = _mm256_blendv_pd(one, _mm256_set1_pd(-1.0), _mm256_cmp_pd(f, _mm256_set1_pd(0.5), _CMP_GE_OQ));
    }
    const __m256d c = _mm256_sub_pd(_mm256_mul_pd(x, nd), _mm256_set1_pd(0.5)), c0 = _mm256_floor_pd(c);
    a.f[h] = _mm256_sub_pd(c, c0);  // place's fraction: 0 from 2^52 on, where floor(c) = c
    // The index clipped to [-2, n + 1] for int32 (clamp / border: past it both taps read the same edge texel or
    // constant, as they do unclipped).
    lo[h] = _mm256_cvttpd_epi32(_mm256_min_pd(_mm256_max_pd(c0, _mm256_set1_pd(-2.0)), _mm256_add_pd(nd, one)));
  }
  const __m256i i = _mm256_set_m128i(lo[1], lo[0]), ni = _mm256_set1_epi32(n), zero = _mm256_setzero_si256();
  const __m256i last = _mm256_set1_epi32(n - 1), all = _mm256_set1_epi32(-1);
  __m256i j = _mm256_add_epi32(i, _mm256_set1_epi32(1)), k = i;
  a.in0 = a.in1 = all;
  if (mode == REPEAT) {  // i in [-1, n - 1], j in [0, n]
    k = _mm256_add_epi32(k, _mm256_and_si256(_mm256_cmpgt_epi32(zero, k), ni));
    j = _mm256_sub_epi32(j, _mm256_andnot_si256(_mm256_cmpgt_epi32(ni, j), ni));
  } else if (mode == BORDER) {
    a.in0 = _mm256_andnot_si256(_mm256_or_si256(_mm256_cmpgt_epi32(zero, k), _mm256_cmpgt_epi32(k, last)), all);
    a.in1 = _mm256_andnot_si256(_mm256_or_si256(_mm256_cmpgt_epi32(zero, j), _mm256_cmpgt_epi32(j, last)), all);
  }
  // mirror (the edge texel is its own image), clamp, and the border's in-range index: clamped
  a.i0 = _mm256_min_epi32(_mm256_max_epi32(k, zero), last);
  a.i1 = _mm256_min_epi32(_mm256_max_epi32(j, zero), last);
}

// Four floats of two halves of doubles (low half first).
DT_AVX2 __m256 to_ps(__m256d a, __m256d b) { return _mm256_set_m128(_mm256_cvtpd_ps(b), _mm256_cvtpd_ps(a)); }

// One level's read of a group: the four taps' texel offsets and (border) masks.
struct Quad8 {
  __m256i idx[4], in[4];
};

DT_AVX2 Quad8 quad8(const Place8& x, const Place8& y, int32_t w) {
  Quad8 t;
  const __m256i W = _mm256_set1_epi32(w), r0 = _mm256_mullo_epi32(y.i0, W), r1 = _mm256_mullo_epi32(y.i1, W);
  t.idx[0] = _mm256_add_epi32(r0, x.i0); t.in[0] = _mm256_and_si256(y.in0, x.in0);
  t.idx[1] = _mm256_add_epi32(r0, x.i1); t.in[1] = _mm256_and_si256(y.in0, x.in1);
  t.idx[2] = _mm256_add_epi32(r1, x.i0); t.in[2] = _mm256_and_si256(y.in1, x.in0);
  t.idx[3] = _mm256_add_epi32(r1, x.i1); t.in[3] = _mm256_and_si256(y.in1, x.in1);
  return t;
}

template <bool kBorder>
DT_AVX2 __m256 tap8(const float* plane, const Quad8& t, int q, __m256 border) {
  if (!kBorder) return _mm256_i32gather_ps(plane, t.idx[q], 4);
  return _mm256_mask_i32gather_ps(border, plane, t.idx[q], _mm256_castsi256_ps(t.in[q]), 4);
}

// The reads of eight points that read the same levels (reads_of's levels), with each point's weights and
// their d / dD.
struct Reads8 {
  int n;
  int64_t k[2];
  alignas(32) double wt[2][8], dwt[2][8];
};

// Level jr's weights of a Reads8's eight points in float32.
DT_AVX2 __m256 level_weight8(const Reads8& r, int jr) {
  return to_ps(_mm256_load_pd(r.wt[jr]), _mm256_load_pd(r.wt[jr] + 4));
}

// reads_of for eight points (D at pd[0 .. 8), or at pd[e[j]] where e is given), in vectors with its
// operations (the same bits), when all read the same levels; false otherwise.
DT_AVX2 bool reads8(const float* pd, const int64_t* e, int64_t K, bool nearest, bool d_grad, Reads8* r) {
  alignas(32) float d8[8];
  if (e != nullptr) {
    for (int j = 0; j < 8; ++j) d8[j] = pd[e[j]];
    pd = d8;
  }
  const __m256d zero = _mm256_setzero_pd(), one = _mm256_set1_pd(1.0);
  const __m256d last = _mm256_set1_pd(static_cast<double>(K - 1));
  __m256d d[2], k[2];
  for (int h = 0; h < 2; ++h) {
    d[h] = _mm256_cvtps_pd(_mm_loadu_ps(pd + 4 * h));
    // floor_capped (-2^52 for NaN) then clamped into [0, K - 1]: max_pd gives 0 for NaN as well
    k[h] = _mm256_min_pd(_mm256_max_pd(_mm256_floor_pd(nearest ? _mm256_add_pd(d[h], _mm256_set1_pd(0.5)) : d[h]),
                                       zero), last);
  }
  const double k0 = _mm256_cvtsd_f64(k[0]);
  const __m256d first = _mm256_set1_pd(k0);
  if ((_mm256_movemask_pd(_mm256_cmp_pd(k[0], first, _CMP_EQ_OQ)) &
       _mm256_movemask_pd(_mm256_cmp_pd(k[1], first, _CMP_EQ_OQ))) != 0xF)
    return false;
  r->k[0] = static_cast<int64_t>(k0);
  __m256d t[2];
  int pair = 0;
  for (int h = 0; h < 2; ++h) {
    t[h] = _mm256_sub_pd(d[h], k[h]);
    pair |= _mm256_movemask_pd(_mm256_cmp_pd(t[h], zero, _CMP_GT_OQ)) << (4 * h);
  }
  if (nearest || k0 >= static_cast<double>(K - 1)) pair = 0;
  if (pair != 0 && pair != 0xFF) return false;  // some between two levels, some on one
  const __m256d minus = _mm256_set1_pd(-1.0);
  for (int h = 0; h < 2; ++h) {
    if (pair) {  // between two levels
      _mm256_store_pd(r->wt[0] + 4 * h, _mm256_sub_pd(one, t[h]));
      _mm256_store_pd(r->wt[1] + 4 * h, t[h]);
      _mm256_store_pd(r->dwt[0] + 4 * h, minus);
      _mm256_store_pd(r->dwt[1] + 4 * h, one);
    } else {  // an integer level: read alone, or with the level below at weight 0 for the derivative
      _mm256_store_pd(r->wt[0] + 4 * h, one);
      _mm256_store_pd(r->wt[1] + 4 * h, zero);
      _mm256_store_pd(r->dwt[0] + 4 * h, nearest ? zero : one);
      _mm256_store_pd(r->dwt[1] + 4 * h, minus);
    }
  }
  if (pair) {
    r->n = 2, r->k[1] = r->k[0] + 1;
  } else if (!nearest && d_grad && k0 > 0) {
    r->n = 2, r->k[1] = r->k[0] - 1;
  } else {
    r->n = 1;
    for (int h = 0; h < 2; ++h) _mm256_store_pd(r->dwt[0] + 4 * h, zero);
  }
  return true;
}

// Whether the points [e, e + 8) go through a forward's eight-point path: finite uv and the same levels (their
// reads in r).
DT_AVX2 bool group_reads8(int64_t e, const float* puv, const float* pd, int64_t K, bool nearest, bool d_grad,
                          Reads8* r) {
  for (int j = 0; j < 8; ++j)
    if (!std::isfinite(puv[2 * (e + j)]) || !std::isfinite(puv[2 * (e + j) + 1])) return false;
  return reads8(pd + e, nullptr, K, nearest, d_grad, r);
}

// The four bilinear weights of eight points' taps on their level jr: wl * (1 - fx) * (1 - fy) ... in double,
// as the scalar loop, then float32.
DT_AVX2 void tap_weights8(const Reads8& r, int jr, const Place8& px, const Place8& py, __m256* w) {
  const double* wl = r.wt[jr];
  __m256d w4[2][4];
  for (int h = 0; h < 2; ++h) {
    const __m256d l = _mm256_load_pd(wl + 4 * h), one = _mm256_set1_pd(1.0);
    const __m256d gx = _mm256_sub_pd(one, px.f[h]), gy = _mm256_sub_pd(one, py.f[h]);
    w4[h][0] = _mm256_mul_pd(_mm256_mul_pd(l, gx), gy);
    w4[h][1] = _mm256_mul_pd(_mm256_mul_pd(l, px.f[h]), gy);
    w4[h][2] = _mm256_mul_pd(_mm256_mul_pd(l, gx), py.f[h]);
    w4[h][3] = _mm256_mul_pd(_mm256_mul_pd(l, px.f[h]), py.f[h]);
  }
  for (int q = 0; q < 4; ++q) w[q] = to_ps(w4[0][q], w4[1][q]);
}

// A group of eight points prepared for its reads: whether it takes the vector path (finite points reading the
// same levels), and then its levels, their taps' texel offsets and their weights.
struct TapGroup8 {
  bool vec;
  int n;
  int64_t k[2];
  Quad8 t[2];
  __m256 w[2][4];
};

// Prepares the group of points [e, e + 8) and prefetches the texel rows it reads (all C planes of each level):
// a block of groups is prepared and prefetched before the block before it is read, so that the misses of
// a block overlap the reads of the one before (as single.cpp's forward). Measured on a 1024^2 RGB texture,
// 512^2 points: a trilinear forward call in 0.78x the time of reading each group as soon as it was placed,
// on one thread and on two. Prefetching the second tap of each row too, or the uv ahead, made it slower.
//
// Only the lines of the group's first and last points are prefetched (kEnds): a point reads the levels where
// its footprint's longer side is 0.5-2 texels, so eight neighbouring pixels' taps on a level lie within about
// 16 texels, on the lines of those two points' taps or between them. A prefetch for every point issued four
// times the instructions for the same lines. Measured (1024^2 RGB texture, 512^2 points of a rotated view, 2
// threads, in one process with and without): the trilinear forward in 0.90x the time in a loop of calls,
// 0.99x after a 30 ms pause; the forward+backward step (prepare_back8 likewise) in 0.91-0.93x in a loop,
// 0.93-0.955x after a pause, 0.93-0.94x on views minified and magnified 4x. Points that are not neighbouring
// pixels, or read a short pyramid's top level far apart, may then miss the cache: time, not bits.
constexpr int kEnds[2] = {0, 7};

DT_AVX2 void prepare_taps8(int64_t e, int64_t C, const std::vector<Level>& L, const std::vector<const float*>& lp,
                           const float* puv, const float* pd, int64_t wrap_u, int64_t wrap_v, bool nearest,
                           bool d_grad, TapGroup8& g) {
  Reads8 r;
  g.vec = group_reads8(e, puv, pd, static_cast<int64_t>(L.size()), nearest, d_grad, &r);
  if (!g.vec) return;
  alignas(32) double u[8], v[8];
  for (int j = 0; j < 8; ++j) u[j] = puv[2 * (e + j)], v[j] = puv[2 * (e + j) + 1];
  g.n = r.n;
  for (int jr = 0; jr < g.n; ++jr) {
    const Level& lv = L[r.k[jr]];
    g.k[jr] = r.k[jr];
    Place8 px, py;
    place8(u, static_cast<int32_t>(lv.w), static_cast<int>(wrap_u), px);
    place8(v, static_cast<int32_t>(lv.h), static_cast<int>(wrap_v), py);
    g.t[jr] = quad8(px, py, static_cast<int32_t>(lv.w));
    tap_weights8(r, jr, px, py, g.w[jr]);
    alignas(32) int32_t o[2][8];  // the first tap of each row (x1 shares its line unless x0 ends one)
    _mm256_store_si256(reinterpret_cast<__m256i*>(o[0]), g.t[jr].idx[0]);
    _mm256_store_si256(reinterpret_cast<__m256i*>(o[1]), g.t[jr].idx[2]);
    const float* p = lp[g.k[jr]];
    for (const int j : kEnds)
      for (int64_t c = 0; c < C; ++c) {
        DT_PREFETCH(p + c * lv.plane + o[0][j], false);
        DT_PREFETCH(p + c * lv.plane + o[1][j], false);
      }
  }
}

// The reads of a prepared vector group into po[c * M + e].
template <int CC, bool kBorder>
DT_AVX2 void read_taps8(const TapGroup8& g, int64_t e, int64_t C, const std::vector<Level>& L,
                        const std::vector<const float*>& lp, float* po, int64_t M, __m256 bv) {
  __m256 acc[CC > 0 ? CC : 1];
  for (int64_t c = 0; c < (CC > 0 ? CC : 1); ++c) acc[c] = _mm256_setzero_ps();
  for (int jr = 0; jr < g.n; ++jr) {
    const Level& lv = L[g.k[jr]];
    const float* p = lp[g.k[jr]];
    for (int64_t c = 0; c < C; ++c) {
      const float* pp = p + c * lv.plane;
      __m256 s = _mm256_setzero_ps();
      for (int q = 0; q < 4; ++q) s = _mm256_add_ps(s, _mm256_mul_ps(g.w[jr][q], tap8<kBorder>(pp, g.t[jr], q, bv)));
      if (CC > 0) {
        acc[c] = _mm256_add_ps(acc[c], s);
      } else {  // run-time channel count: accumulate in the output
        float* o = po + c * M + e;
        _mm256_storeu_ps(o, jr == 0 ? s : _mm256_add_ps(_mm256_loadu_ps(o), s));
      }
    }
  }
  if (CC > 0)
    for (int64_t c = 0; c < C; ++c) _mm256_storeu_ps(po + c * M + e, acc[c]);
}

constexpr int kTapGroups = 8;  // groups of eight points a block

// The groups of eight points starting at lo, lo + 8, ... (below end), in_two_blocks of kTapGroups:
// prepare(first, group) prepares a group and prefetches its lines, read(group, first) reads it.
template <typename G, typename Prepare, typename Read>
DT_AVX2 void groups_of_eight(int64_t lo, int64_t end, Prepare&& prepare, Read&& read) {
  int64_t next = lo, e = lo;
  in_two_blocks<G, kTapGroups>(
      [&](G* b) __attribute__((target("avx2,fma"))) {
        const int n = static_cast<int>(std::min<int64_t>(kTapGroups, (end - next) / 8));
        for (int i = 0; i < n; ++i, next += 8) prepare(next, b[i]);
        return n;
      },
      [&](const G& g) __attribute__((target("avx2,fma"))) {
        read(g, e);
        e += 8;
      });
}

// The forward of points [lo, hi) with one tap each, float32, by groups_of_eight. Groups on mixed
// levels or holding a non-finite point, and the tail, go through the scalar loop.
template <int CC, bool kBorder>
__attribute__((target("avx2,fma"))) void forward_range_avx2(int64_t lo, int64_t hi, int64_t Cdyn,
                                                            const std::vector<Level>& L,
                                                            const std::vector<const float*>& lp, const float* puv,
                                                            const float* pd, float* po, int64_t M, int64_t wrap_u,
                                                            int64_t wrap_v, double border, bool nearest, bool d_grad) {
  const int64_t C = CC > 0 ? CC : Cdyn;
  const __m256 bv = _mm256_set1_ps(static_cast<float>(border));
  const int64_t end = lo + (hi - lo) / 8 * 8;
  groups_of_eight<TapGroup8>(
      lo, end,
      [&](int64_t e, TapGroup8& g) __attribute__((target("avx2,fma"))) {
        prepare_taps8(e, C, L, lp, puv, pd, wrap_u, wrap_v, nearest, d_grad, g);
      },
      [&](const TapGroup8& g, int64_t e) __attribute__((target("avx2,fma"))) {
        if (g.vec)
          read_taps8<CC, kBorder>(g, e, C, L, lp, po, M, bv);
        else
          forward_range<float, CC, kBorder>(e, e + 8, C, L, lp, puv, pd, nullptr, nullptr, po, M, wrap_u, wrap_v,
                                            border, nearest, d_grad);
      });
  if (end < hi)
    forward_range<float, CC, kBorder>(end, hi, C, L, lp, puv, pd, nullptr, nullptr, po, M, wrap_u, wrap_v, border,
                                      nearest, d_grad);
}

// Eight stochastic draws (float32) placed for their reads: the draws and tap positions point by point
// (draw_of, in double as place_draw), then per drawn level (at most two in a group: neighbouring pixels' D
// differ by less than one) the taps of all eight lanes placed in vectors (place8: the scalar placement's
// bits), read in the lanes on that level (masked gathers) and blended. vec is false where a uv is not finite
// or the eight drew three levels: those go through forward_draws.
struct DrawGroup8 {
  bool vec;
  int n;
  int64_t k[2];
  Quad8 t[2];
  __m256 w[2][4];
  __m256 lane[2];
  __m256 scale;
  // Two levels whose texels lie within int32 offsets of the first level's (the usual case: both are
  // allocations of one process): the lanes' taps merged into one set of offsets from lp[k[0]], and each
  // lane's channel stride, so that a channel costs four gathers, as on one level.
  bool merged;
  Quad8 m;
  __m256i plane;
  __m256 w1[4];
};

DT_AVX2 void prepare_draws8(int64_t e, int64_t C, const std::vector<Level>& L, const std::vector<const float*>& lp,
                            const float* puv, const float* pd, int64_t wrap_u, int64_t wrap_v, const ReadOptions& o,
                            DrawGroup8& g) {
  const int64_t K = static_cast<int64_t>(L.size());
  alignas(32) double u[8], v[8];
  alignas(32) float sc[8];
  alignas(32) int32_t in_level[2][8];
  int64_t kk[8];
  g.vec = false;
  for (int j = 0; j < 8; ++j) {
    const int64_t p = e + j;
    const double pu = puv[2 * p], pv = puv[2 * p + 1];
    if (!std::isfinite(pu) || !std::isfinite(pv)) return;
    const Draw<float> dr = draw_of<float>(o, p, pd[p], K);
    kk[j] = dr.r.k[0];
    sc[j] = dr.scale;
    u[j] = pu;
    v[j] = pv;
  }
  // The lanes' levels, without a branch per lane (the levels are coin tosses): the first lane's, and any other.
  g.k[0] = kk[0];
  g.k[1] = kk[0];
  for (int j = 1; j < 8; ++j) g.k[1] = kk[j] != kk[0] ? kk[j] : g.k[1];
  bool ok = true;
  for (int j = 0; j < 8; ++j) {
    ok = ok && (kk[j] == g.k[0] || kk[j] == g.k[1]);
    in_level[0][j] = -static_cast<int32_t>(kk[j] == g.k[0]);
    in_level[1][j] = -static_cast<int32_t>(kk[j] != g.k[0]);
  }
  if (!ok) return;
  g.n = g.k[1] != g.k[0] ? 2 : 1;
  g.scale = _mm256_load_ps(sc);
  Reads8 ones;  // weight 1 in every lane: forward_draws's wl
  for (int j = 0; j < 8; ++j) ones.wt[0][j] = 1.0;
  for (int jr = 0; jr < g.n; ++jr) {
    const Level& lv = L[g.k[jr]];
    Place8 px, py;
    place8(u, static_cast<int32_t>(lv.w), static_cast<int>(wrap_u), px);
    place8(v, static_cast<int32_t>(lv.h), static_cast<int>(wrap_v), py);
    g.t[jr] = quad8(px, py, static_cast<int32_t>(lv.w));
    tap_weights8(ones, 0, px, py, g.w[jr]);
    g.lane[jr] = _mm256_castsi256_ps(_mm256_load_si256(reinterpret_cast<const __m256i*>(in_level[jr])));
    alignas(32) int32_t r[2][8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(r[0]), g.t[jr].idx[0]);
    _mm256_store_si256(reinterpret_cast<__m256i*>(r[1]), g.t[jr].idx[2]);
    const float* p = lp[g.k[jr]];
    for (int j = 0; j < 8; ++j) {
      if (!in_level[jr][j]) continue;
      for (int64_t c = 0; c < C; ++c) {
        DT_PREFETCH(p + c * lv.plane + r[0][j], false);
        DT_PREFETCH(p + c * lv.plane + r[1][j], false);
      }
    }
  }
  g.merged = false;
  if (g.n == 2) {
    const int64_t diff = lp[g.k[1]] - lp[g.k[0]], p0 = L[g.k[0]].plane, p1 = L[g.k[1]].plane;
    const int64_t lo = std::min<int64_t>(0, diff), hi = std::max<int64_t>(C * p0, diff + C * p1);
    if (lo > -(int64_t(1) << 31) && hi < (int64_t(1) << 31)) {
      g.merged = true;
      const __m256i sel = _mm256_castps_si256(g.lane[1]);
      const __m256i shift = _mm256_and_si256(sel, _mm256_set1_epi32(static_cast<int32_t>(diff)));
      for (int q = 0; q < 4; ++q) {
        g.m.idx[q] = _mm256_add_epi32(_mm256_blendv_epi8(g.t[0].idx[q], g.t[1].idx[q], sel), shift);
        g.m.in[q] = _mm256_blendv_epi8(g.t[0].in[q], g.t[1].in[q], sel);
        g.w1[q] = _mm256_blendv_ps(g.w[0][q], g.w[1][q], g.lane[1]);
      }
      g.plane = _mm256_blendv_epi8(_mm256_set1_epi32(static_cast<int32_t>(p0)),
                                   _mm256_set1_epi32(static_cast<int32_t>(p1)), sel);
    }
  }
  g.vec = true;
}

// The reads of a prepared group of draws into po[c * M + e]: forward_draws's sums in its order, lane by lane.
template <bool kBorder>
DT_AVX2 void read_draws8(const DrawGroup8& g, int64_t e, int64_t C, const std::vector<Level>& L,
                         const std::vector<const float*>& lp, float* po, int64_t M, __m256 bv) {
  const __m256 zero = _mm256_setzero_ps();
  if (g.merged) {
    const float* base = lp[g.k[0]];
    __m256i off = _mm256_setzero_si256();
    for (int64_t c = 0; c < C; ++c, off = _mm256_add_epi32(off, g.plane)) {
      __m256 s = zero;
      for (int q = 0; q < 4; ++q) {
        const __m256i idx = _mm256_add_epi32(g.m.idx[q], off);
        const __m256 t = kBorder ? _mm256_mask_i32gather_ps(bv, base, idx, _mm256_castsi256_ps(g.m.in[q]), 4)
                                 : _mm256_i32gather_ps(base, idx, 4);
        s = _mm256_add_ps(s, _mm256_mul_ps(g.w1[q], t));
      }
      _mm256_storeu_ps(po + c * M + e, _mm256_mul_ps(_mm256_add_ps(zero, s), g.scale));
    }
    return;
  }
  for (int64_t c = 0; c < C; ++c) {
    __m256 out = zero;
    for (int jr = 0; jr < g.n; ++jr) {
      const float* pp = lp[g.k[jr]] + c * L[g.k[jr]].plane;
      __m256 s = zero;
      for (int q = 0; q < 4; ++q) {
        __m256 t;
        if (g.n == 1) {
          t = tap8<kBorder>(pp, g.t[jr], q, bv);
        } else {
          const __m256 mask = kBorder ? _mm256_and_ps(g.lane[jr], _mm256_castsi256_ps(g.t[jr].in[q])) : g.lane[jr];
          t = _mm256_mask_i32gather_ps(kBorder ? bv : zero, pp, g.t[jr].idx[q], mask, 4);
        }
        s = _mm256_add_ps(s, _mm256_mul_ps(g.w[jr][q], t));
      }
      out = g.n == 1 ? s : _mm256_blendv_ps(out, s, g.lane[jr]);
    }
    _mm256_storeu_ps(po + c * M + e, _mm256_mul_ps(_mm256_add_ps(zero, out), g.scale));
  }
}

// The stochastic forward of points [lo, hi), float32, by groups_of_eight (the same bits as forward_draws).
template <int CC, bool kBorder>
__attribute__((target("avx2,fma"))) void forward_draws_avx2(int64_t lo, int64_t hi, int64_t C,
                                                            const std::vector<Level>& L,
                                                            const std::vector<const float*>& lp, const float* puv,
                                                            const float* pd, float* po, int64_t M, int64_t wrap_u,
                                                            int64_t wrap_v, double border, const ReadOptions& o) {
  const __m256 bv = _mm256_set1_ps(static_cast<float>(border));
  const int64_t end = lo + (hi - lo) / 8 * 8;
  groups_of_eight<DrawGroup8>(
      lo, end,
      [&](int64_t e, DrawGroup8& g) __attribute__((target("avx2,fma"))) {
        prepare_draws8(e, C, L, lp, puv, pd, wrap_u, wrap_v, o, g);
      },
      [&](const DrawGroup8& g, int64_t e) __attribute__((target("avx2,fma"))) {
        if (g.vec)
          read_draws8<kBorder>(g, e, C, L, lp, po, M, bv);
        else
          forward_draws<float, CC, kBorder>(e, e + 8, C, L, lp, puv, pd, po, M, wrap_u, wrap_v, border, o);
      });
  if (end < hi) forward_draws<float, CC, kBorder>(end, hi, C, L, lp, puv, pd, po, M, wrap_u, wrap_v, border, o);
}

// The taps of eight points with N_j taps each along their axes: tap i at uv + o_i * axis with
// o_i = tap_offset(i, N_j), in vectors with the scalar loop's operations (division, product, sum: the same bits).
struct TapLine8 {
  __m256d u[2], v[2], au[2], av[2], n[2];
  __m256i n32;
  // The eight points' uv, axis and tap counts N.
  DT_AVX2 TapLine8(const double* pu, const double* pv, const double* pau, const double* pav, const int64_t* N) {
    alignas(32) double nd[8];
    alignas(32) int32_t c[8];
    for (int j = 0; j < 8; ++j) nd[j] = static_cast<double>(N[j]), c[j] = static_cast<int32_t>(N[j]);
    for (int h = 0; h < 2; ++h) {
      u[h] = _mm256_loadu_pd(pu + 4 * h), v[h] = _mm256_loadu_pd(pv + 4 * h);
      au[h] = _mm256_loadu_pd(pau + 4 * h), av[h] = _mm256_loadu_pd(pav + 4 * h);
      n[h] = _mm256_load_pd(nd + 4 * h);
    }
    n32 = _mm256_load_si256(reinterpret_cast<const __m256i*>(c));
  }
  // Tap i's coordinates into tu, tv [8] and its offsets o (two halves).
  DT_AVX2 void place(int64_t i, double* tu, double* tv, __m256d* o) const {
    const __m256d k = _mm256_set1_pd(static_cast<double>(i) + 0.5), half = _mm256_set1_pd(0.5);
    for (int h = 0; h < 2; ++h) {
      o[h] = _mm256_sub_pd(_mm256_div_pd(k, n[h]), half);
      _mm256_store_pd(tu + 4 * h, _mm256_add_pd(u[h], _mm256_mul_pd(o[h], au[h])));
      _mm256_store_pd(tv + 4 * h, _mm256_add_pd(v[h], _mm256_mul_pd(o[h], av[h])));
    }
  }
  // The lanes with a tap i (all ones).
  DT_AVX2 __m256i on(int64_t i) const { return _mm256_cmpgt_epi32(n32, _mm256_set1_epi32(static_cast<int32_t>(i))); }
  // The same as two halves of four 64-bit lanes.
  DT_AVX2 void on_pd(int64_t i, __m256d* m) const {
    const __m256d k = _mm256_set1_pd(static_cast<double>(i));
    for (int h = 0; h < 2; ++h) m[h] = _mm256_cmp_pd(k, n[h], _CMP_LT_OQ);
  }
};

// The forward of points [lo, hi) with N taps each (anisotropic, auto: count pc, axis pa), float32, eight
// points at a time where the eight read the same levels (most groups: the level follows the footprint); the
// channel count fixed at compile time (CC > 0). Tap i runs in the lanes with i < N_j. It is placed as the
// scalar loop places it (u + o_i * axis in double, then fold and place) and the sums run in its order, so a
// point gives the same bits on either path. Other groups, the tail and CC = 0 go through the scalar loop.
// Measured on a 1024^2 RGB texture, 512^2 points, 4 taps a point: an anisotropic forward call in 0.50x the
// scalar loop's time on one thread and on two, auto in 0.54x.
template <int CC, bool kBorder>
__attribute__((target("avx2,fma"))) void forward_taps_avx2(int64_t lo, int64_t hi, int64_t Cdyn,
                                                           const std::vector<Level>& L,
                                                           const std::vector<const float*>& lp, const float* puv,
                                                           const float* pd, const int64_t* pc, const float* pa,
                                                           float* po, int64_t M, int64_t wrap_u, int64_t wrap_v,
                                                           double border, bool nearest, bool d_grad) {
  const __m256 bv = _mm256_set1_ps(static_cast<float>(border));
  const int64_t K = static_cast<int64_t>(L.size());
  int64_t e = lo;
  for (; CC > 0 && e + 8 <= hi; e += 8) {
    Reads8 r;
    if (!group_reads8(e, puv, pd, K, nearest, d_grad, &r)) {
      forward_range<float, CC, kBorder>(e, e + 8, CC, L, lp, puv, pd, pc, pa, po, M, wrap_u, wrap_v, border,
                                        nearest, d_grad);
      continue;
    }
    alignas(32) int64_t N[8];
    alignas(32) float nfl[8];
    int64_t most = 0, fewest = std::numeric_limits<int64_t>::max();
    for (int j = 0; j < 8; ++j) {
      N[j] = tap_count(pc, e + j);
      nfl[j] = static_cast<float>(N[j]);
      most = std::max(most, N[j]), fewest = std::min(fewest, N[j]);
    }
    __m256 acc[CC > 0 ? CC : 1];
    for (int c = 0; c < CC; ++c) acc[c] = _mm256_setzero_ps();
    alignas(32) double u[8], v[8], au[8], av[8];
    for (int j = 0; j < 8; ++j) {
      u[j] = puv[2 * (e + j)], v[j] = puv[2 * (e + j) + 1];
      au[j] = pa[2 * (e + j)], av[j] = pa[2 * (e + j) + 1];
    }
    const TapLine8 line(u, v, au, av, N);
    for (int64_t i = 0; i < most; ++i) {
      alignas(32) double tu[8], tv[8];
      __m256d o[2];
      line.place(i, tu, tv, o);
      const __m256 mask = _mm256_castsi256_ps(line.on(i));
      for (int jr = 0; jr < r.n; ++jr) {
        const Level& lv = L[r.k[jr]];
        Place8 px, py;
        place8(tu, static_cast<int32_t>(lv.w), static_cast<int>(wrap_u), px);
        place8(tv, static_cast<int32_t>(lv.h), static_cast<int>(wrap_v), py);
        const Quad8 t = quad8(px, py, static_cast<int32_t>(lv.w));
        __m256 w[4];
        tap_weights8(r, jr, px, py, w);
        const float* p = lp[r.k[jr]];
        for (int c = 0; c < CC; ++c) {
          const float* pp = p + c * lv.plane;
          __m256 s = _mm256_setzero_ps();
          for (int q = 0; q < 4; ++q) s = _mm256_add_ps(s, _mm256_mul_ps(w[q], tap8<kBorder>(pp, t, q, bv)));
          acc[c] = i < fewest ? _mm256_add_ps(acc[c], s) : _mm256_blendv_ps(acc[c], _mm256_add_ps(acc[c], s), mask);
        }
      }
    }
    const __m256 n = _mm256_load_ps(nfl);
    for (int c = 0; c < CC; ++c) _mm256_storeu_ps(po + c * M + e, _mm256_div_ps(acc[c], n));
  }
  if (e < hi)
    forward_range<float, CC, kBorder>(e, hi, Cdyn, L, lp, puv, pd, pc, pa, po, M, wrap_u, wrap_v, border, nearest,
                                      d_grad);
}

#endif

// Whether float32 reads of these levels can take the eight-point paths (on, float32, int32 texel offsets).
bool simd_levels(const Tensor& uv, const std::vector<Tensor>& levels) {
  if (!(simd_on() && uv.scalar_type() == kFloat32)) return false;
  for (const auto& t : levels)
    if (t.size(1) * t.size(2) >= (int64_t(1) << 31)) return false;
  return true;
}

// Whether a one-tap read (no counts) goes through the eight-point path.
bool simd_taps(const Tensor& uv, const Tensor& count, const std::vector<Tensor>& levels) {
  return count.numel() == 0 && simd_levels(uv, levels);
}

}  // namespace

Tensor forward(std::vector<Tensor> levels, Tensor uv, Tensor D, Tensor axis,
                      Tensor count, const ReadOptions& opts) {
  const int64_t wrap_u = opts.wrap_u, wrap_v = opts.wrap_v;
  const double border = opts.border;
  const bool nearest = opts.nearest, d_grad = opts.d_grad;
  auto L = shapes(levels, uv, D, axis, count);
  const int64_t C = levels[0].size(0), M = uv.size(0);
  DT_CHECK(!opts.stochastic || count.numel() == 0, "mip_read: a stochastic draw takes no counts");
  auto out = empty({C, M}, options_of(uv));
  // A stochastic draw reads one tap on a level drawn point by point: neighbouring points seldom share their
  // level, which the deterministic eight-point paths need; forward_draws(_avx2) read them.
  const bool sto = opts.stochastic;
  const bool simd = !sto && simd_taps(uv, count, levels);
  const bool simd_n = !sto && simd_levels(uv, levels) && count.numel() != 0;
  const bool sto_simd = sto && simd_levels(uv, levels);  // forward_draws_avx2: a level per lane
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_forward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.mutable_data_ptr<scalar_t>());
    const scalar_t* puv = uv.mutable_data_ptr<scalar_t>();
    const scalar_t* pd = D.mutable_data_ptr<scalar_t>();
    const int64_t* pc = count.numel() ? count.mutable_data_ptr<int64_t>() : nullptr;
    const scalar_t* pa = pc ? axis.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
      specialized(C, wrap_u, wrap_v, [&](auto cc, auto border_) {
        constexpr int CC = decltype(cc)::value;
        constexpr bool kB = decltype(border_)::value;
#if DT_HAVE_AVX2
        if constexpr (std::is_same_v<scalar_t, float>) {
          if (sto_simd) return forward_draws_avx2<CC, kB>(lo, hi, C, L, lp, puv, pd, po, M, wrap_u, wrap_v, border,
                                                          opts);
          if (simd) return forward_range_avx2<CC, kB>(lo, hi, C, L, lp, puv, pd, po, M, wrap_u, wrap_v, border,
                                                       nearest, d_grad);
          if (simd_n) return forward_taps_avx2<CC, kB>(lo, hi, C, L, lp, puv, pd, pc, pa, po, M, wrap_u, wrap_v,
                                                      border, nearest, d_grad);
        }
#endif
        if (sto)
          return forward_draws<scalar_t, CC, kB>(lo, hi, C, L, lp, puv, pd, po, M, wrap_u, wrap_v, border, opts);
        forward_range<scalar_t, CC, kB>(lo, hi, C, L, lp, puv, pd, pc, pa, po, M, wrap_u, wrap_v, border, nearest,
                                        d_grad);
      });
    });
  });
  return out;
}

Tensor probe_offsets(Tensor count, Tensor like, uint64_t seed, int64_t first, int64_t strata) {
  DT_CHECK(count.dim() == 1 && count.is_contiguous() && count.scalar_type() == kInt64,
           "probe_offsets: count must be contiguous int64 [M]");
  DT_CHECK(strata >= 1 && first >= 0, "probe_offsets: expected strata >= 1 and first >= 0");
  const int64_t M = count.size(0);
  auto out = empty({M}, options_of(like));
  DT_DISPATCH_FLOATING_TYPES(like.scalar_type(), "probe_offsets", [&] {
    const int64_t* pc = count.mutable_data_ptr<int64_t>();
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    parallel_for(0, M, 8192, [&](int64_t lo, int64_t hi) {
      for (int64_t e = lo; e < hi; ++e) {
        const int64_t N = tap_count(pc, e);
        const double n = static_cast<double>(N);
        double i = floor_capped(stratified_uniform(seed, first + e, strata) * n);
        i = i > n - 1 ? n - 1 : i;
        po[e] = static_cast<scalar_t>(tap_offset(static_cast<int64_t>(i), N));
      }
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

// One bilinear tap's backward over the C channels of level lv (texels p, level gradient gk, null where
// not needed), the output gradients g: the texel gradients g * wl * (bilinear weight) scattered into gk,
// and the g-weighted sums of the tap's slopes along x and y (per texel of the level) and of its value,
// which the callers turn into uv and level derivatives.
template <typename scalar_t, bool kBorder>
DT_INLINE void tap_backward(const Bilinear& b, const Level& lv, const scalar_t* p, scalar_t* gk, const scalar_t* g,
                            int64_t C, scalar_t wl, scalar_t bv, scalar_t& sx, scalar_t& sy, scalar_t& sv) {
  const scalar_t fx = static_cast<scalar_t>(b.fx), fy = static_cast<scalar_t>(b.fy);
  const scalar_t w[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
  sx = 0, sy = 0, sv = 0;
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
}

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
      scalar_t sx, sy, sv;
      tap_backward<scalar_t, kBorder>(b, lv, lp[k], out.gp[k], g, C, static_cast<scalar_t>(r.wt[j]), bv, sx, sy, sv);
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

// A placed stochastic draw's backward (the forward's draw again, from the same counters): backward_point's
// arithmetic for its one tap of weight w / p and level derivative d(w / p) / dD = +-1 / p, so the texel
// gradients are (g w / p) times the bilinear weights, as the torch path's product (tap * level_weight) gives.
template <typename scalar_t, int CC, bool kBorder>
DT_INLINE void backward_draw(const Placed<scalar_t>& q, int64_t e, int64_t Cdyn, const std::vector<Level>& L,
                             const std::vector<const scalar_t*>& lp, const scalar_t* pg, const Grads<scalar_t>& out,
                             int64_t gsc, int64_t gsm, double border) {
  if (!q.live) return;
  const int64_t C = CC > 0 ? CC : Cdyn;
  const scalar_t bv = static_cast<scalar_t>(border);
  std::vector<scalar_t> heap(CC > 0 ? 0 : C);
  scalar_t stack[CC > 0 ? CC : 1];
  scalar_t* g = CC > 0 ? stack : heap.data();
  bool any = false;
  for (int64_t c = 0; c < C; ++c) {
    g[c] = pg[c * gsc + e * gsm] / static_cast<scalar_t>(1);
    any = any || g[c] != 0;
  }
  if (!any) return;
  const Level& lv = L[q.k];
  const Bilinear& b = q.b;
  const double wt = static_cast<double>(q.scale);
  scalar_t sx, sy, sv;
  tap_backward<scalar_t, kBorder>(b, lv, lp[q.k], out.gp[q.k], g, C, static_cast<scalar_t>(wt), bv, sx, sy, sv);
  double du = 0, dv = 0, dD = 0;
  du += wt * sx * b.sx * static_cast<double>(lv.w);
  dv += wt * sy * b.sy * static_cast<double>(lv.h);
  dD += q.dscale * sv;
  if (out.uv) {
    out.uv[2 * e] = static_cast<scalar_t>(0.0 + du);
    out.uv[2 * e + 1] = static_cast<scalar_t>(0.0 + dv);
  }
  if (out.D) out.D[e] = static_cast<scalar_t>(dD);
}

// The taps' level-gradient scatter uses bands.h's ScaleBands: a point
// writes rows of up to two levels, around its taps' v range (N taps along
// the axis); the bands are fractions of the texture height, the same on
// every level.

// floor(a / b) for b > 0 and |a| < 2^50, given inv_b = 1 / b: the product a * inv_b is within 2^-10 of
// a / b, so its floor is off by at most one, which two integer products correct exactly (measured: 64-bit
// integer divisions, then double divisions, were a third of the band-key pass).
DT_INLINE int64_t floor_div(int64_t a, int64_t b, double inv_b) {
  int64_t q = static_cast<int64_t>(floor_capped(static_cast<double>(a) * inv_b));
  q -= q * b > a;
  q += (q + 1) * b <= a;
  return q;
}

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
  const double n = static_cast<double>(h), fa = floor_capped(lo * n - 0.5);
  *a = static_cast<int64_t>(fa) - 1;
  *b = static_cast<int64_t>(hi == lo ? fa : floor_capped(hi * n - 0.5)) + 2;
  if (mode != REPEAT) {
    *a = std::min(std::max<int64_t>(*a, 0), h - 1);
    *b = std::min(std::max<int64_t>(*b, 0), h - 1);
  }
}

// Point e's band key (ScaleBands), or -1 where it writes nothing. inv_h[k] = 1 / L[k].h.
DT_INLINE int32_t tap_key(const ScaleBands& T, const std::vector<Level>& L, const double* inv_h, double u, double v,
                          const Reads& r, int64_t N, double av, int wrap_v) {
  if (!std::isfinite(u) || !std::isfinite(v)) return -1;
  const double half = N > 1 ? std::abs(av) * (0.5 - 0.5 / static_cast<double>(N)) : 0.0;
  double lo = v - half, hi = v + half;
  if (!std::isfinite(lo) || !std::isfinite(hi)) return static_cast<int32_t>(T.serial);
  if (wrap_v == REPEAT || wrap_v == MIRROR) {
    const double period = wrap_v == REPEAT ? 1.0 : 2.0;
    if (!(hi - lo < period)) return static_cast<int32_t>(T.serial);
    if (wrap_v == REPEAT) {
      // Whole periods off exactly: std::floor is exact for every finite double, where floor_capped stops at
      // 2^52 and would leave |v| >= 2^52 in lo / hi (rows ~2^52, outside floor_div's |a| < 2^50).
      const double s = std::floor(v);
      lo -= s;
      hi -= s;
    }
  }
  int64_t a[2], b[2];
  for (int j = 0; j < r.n; ++j) rows_of(lo, hi, L[r.k[j]].h, wrap_v, &a[j], &b[j]);
  int64_t nb = T.nb0;
  for (int64_t s = 0; s < T.scales; ++s, nb /= 2) {
    int64_t band = std::numeric_limits<int64_t>::max();
    for (int j = 0; j < r.n; ++j) band = std::min(band, floor_div(a[j] * nb, L[r.k[j]].h, inv_h[r.k[j]]));
    bool fits = true;
    for (int j = 0; j < r.n; ++j) fits = fits && (b[j] + 1) * nb <= (band + 2) * L[r.k[j]].h;
    if (fits) {
      // band mod nb in one step whatever band is (nb is a power of two, band_count; the mask is the
      // non-negative remainder of a negative band too): no loop whose trip count grows with v (issue 42).
      band &= nb - 1;
      return static_cast<int32_t>(T.offset[s] + band);
    }
  }
  return static_cast<int32_t>(T.serial);
}

#if DT_HAVE_AVX2
// One level's taps of eight points, placed (common.h fold + place, in double): the fractions (float32, as the
// weights use them), the fold slopes (two halves of doubles) and the texel offsets.
struct Level8 {
  __m256 fx, fy;
  __m256d sx[2], sy[2];
  Quad8 t;
};

DT_AVX2 void level8(const double* u, const double* v, const Level& lv, int64_t wrap_u, int64_t wrap_v, Level8& a) {
  Place8 px, py;
  place8(u, static_cast<int32_t>(lv.w), static_cast<int>(wrap_u), px);
  place8(v, static_cast<int32_t>(lv.h), static_cast<int>(wrap_v), py);
  a.t = quad8(px, py, static_cast<int32_t>(lv.w));
  a.fx = to_ps(px.f[0], px.f[1]), a.fy = to_ps(py.f[0], py.f[1]);
  for (int h = 0; h < 2; ++h) a.sx[h] = px.slope[h], a.sy[h] = py.slope[h];
}

// One level's part of eight points' backward (backward8, backward_taps8), as backward_point does it: the
// taps a on level lv (texels p) read per channel; du, dv and dD get wt * sum_c g_c * d value / d u (times the
// fold slope and the level's width), likewise along v, and dwt * sum_c g_c * value, in double (dD only in
// the lanes of mask, two halves, where given); where share is given, share[c][q] gets channel c's
// texel-gradient shares g_c * wl * w_q.
template <bool kBorder>
DT_AVX2 void level_grads8(const Level8& a, const Level& lv, const float* p, int64_t C, const __m256* g, __m256 wl,
                          __m256 bv, const double* wt, const double* dwt, float (*share)[4][8], __m256d* du,
                          __m256d* dv, __m256d* dD, const __m256d* mask = nullptr) {
  const __m256 one = _mm256_set1_ps(1.0f);
  const __m256 fx = a.fx, fy = a.fy;
  const __m256 gx = _mm256_sub_ps(one, fx), gy = _mm256_sub_ps(one, fy);
  const __m256 w[4] = {_mm256_mul_ps(gx, gy), _mm256_mul_ps(fx, gy), _mm256_mul_ps(gx, fy), _mm256_mul_ps(fx, fy)};
  __m256 sx = _mm256_setzero_ps(), sy = _mm256_setzero_ps(), sv = _mm256_setzero_ps();
  for (int64_t c = 0; c < C; ++c) {
    const float* pp = p + c * lv.plane;
    __m256 tq[4];
    for (int q = 0; q < 4; ++q) tq[q] = tap8<kBorder>(pp, a.t, q, bv);
    const __m256 ex = _mm256_add_ps(_mm256_mul_ps(gy, _mm256_sub_ps(tq[1], tq[0])),
                                    _mm256_mul_ps(fy, _mm256_sub_ps(tq[3], tq[2])));
    const __m256 ey = _mm256_add_ps(_mm256_mul_ps(gx, _mm256_sub_ps(tq[2], tq[0])),
                                    _mm256_mul_ps(fx, _mm256_sub_ps(tq[3], tq[1])));
    __m256 ev = _mm256_mul_ps(w[0], tq[0]);
    for (int q = 1; q < 4; ++q) ev = _mm256_add_ps(ev, _mm256_mul_ps(w[q], tq[q]));
    sx = _mm256_add_ps(sx, _mm256_mul_ps(g[c], ex));
    sy = _mm256_add_ps(sy, _mm256_mul_ps(g[c], ey));
    sv = _mm256_add_ps(sv, _mm256_mul_ps(g[c], ev));
    if (share == nullptr) continue;
    const __m256 gw = _mm256_mul_ps(g[c], wl);
    for (int q = 0; q < 4; ++q) _mm256_storeu_ps(share[c][q], _mm256_mul_ps(gw, w[q]));
  }
  const __m256d nw = _mm256_set1_pd(static_cast<double>(lv.w)), nh = _mm256_set1_pd(static_cast<double>(lv.h));
  const __m128 hx[2] = {_mm256_castps256_ps128(sx), _mm256_extractf128_ps(sx, 1)};
  const __m128 hy[2] = {_mm256_castps256_ps128(sy), _mm256_extractf128_ps(sy, 1)};
  const __m128 hv[2] = {_mm256_castps256_ps128(sv), _mm256_extractf128_ps(sv, 1)};
  for (int h = 0; h < 2; ++h) {
    const __m256d wa = _mm256_loadu_pd(wt + 4 * h), da = _mm256_loadu_pd(dwt + 4 * h);
    du[h] = _mm256_add_pd(du[h], _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(wa, _mm256_cvtps_pd(hx[h])), a.sx[h]), nw));
    dv[h] = _mm256_add_pd(dv[h], _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(wa, _mm256_cvtps_pd(hy[h])), a.sy[h]), nh));
    const __m256d sum = _mm256_add_pd(dD[h], _mm256_mul_pd(da, _mm256_cvtps_pd(hv[h])));
    dD[h] = mask == nullptr ? sum : _mm256_blendv_pd(dD[h], sum, mask[h]);
  }
}

// A group of eight points (one tap each, float32) prepared for backward8: whether it takes the vector path
// (finite points reading the same levels), and then its levels, their weights and their placed taps.
struct BackGroup8 {
  bool vec;
  Reads8 r;
  Level8 lv[2];
};

// Prepares the group of points e[0..8) for backward8 and prefetches the lines it reads (the output gradient;
// the levels, where reads) and writes (the level gradients): a block of groups is prepared and prefetched
// before the block before it is read, so that its misses overlap that block's work (as single.cpp's
// backward). Measured on a 1024^2 RGB texture, 512^2 points of a rotated view: a trilinear forward+backward
// step in 0.86-0.98x the time of placing each group's taps twice (a prefetch two groups ahead, then the
// read) without the output gradient's prefetch, on one thread and on two. The channel count is fixed at compile
// time where the kernel has it (CC), which unrolls the prefetch loop: the step in 0.96x the time of a run-time
// count (same case, 2 threads, in one process with and without; also with the view magnified 4x). Only the
// group's first and last points' lines are prefetched, as prepare_taps8 does.
template <int CC>
DT_AVX2 void prepare_back8(const int64_t* e, int64_t Cdyn, const std::vector<Level>& L,
                           const std::vector<const float*>& lp, const float* puv, const float* pd, const float* pg,
                           int64_t gsc, int64_t gsm, const Grads<float>& out, int64_t wrap_u, int64_t wrap_v,
                           bool nearest, bool d_grad, bool reads, BackGroup8& g) {
  const int64_t C = CC > 0 ? CC : Cdyn;
  alignas(32) double u[8], v[8];
  g.vec = false;
  for (int j = 0; j < 8; ++j) {
    u[j] = puv[2 * e[j]], v[j] = puv[2 * e[j] + 1];
    if (!std::isfinite(u[j]) || !std::isfinite(v[j])) return;
  }
  if (!reads8(pd, e, static_cast<int64_t>(L.size()), nearest, d_grad, &g.r)) return;
  g.vec = true;
  // A band's points come in runs along the pixel rows: a group's output gradients mostly share a line.
  for (int64_t c = 0; c < C; ++c) {
    DT_PREFETCH(pg + c * gsc + e[0] * gsm, false);
    if (e[7] - e[0] != 7) DT_PREFETCH(pg + c * gsc + e[7] * gsm, false);
  }
  for (int jr = 0; jr < g.r.n; ++jr) {
    const int64_t k = g.r.k[jr];
    const Level& lv = L[k];
    level8(u, v, lv, wrap_u, wrap_v, g.lv[jr]);
    alignas(32) int32_t o[2][8];  // the first tap of each row
    _mm256_store_si256(reinterpret_cast<__m256i*>(o[0]), g.lv[jr].t.idx[0]);
    _mm256_store_si256(reinterpret_cast<__m256i*>(o[1]), g.lv[jr].t.idx[2]);
    for (const int j : kEnds)
      for (int row = 0; row < 2; ++row)
        for (int64_t c = 0; c < C; ++c) {
          if (reads) DT_PREFETCH(lp[k] + c * lv.plane + o[row][j], false);
          if (out.gp[k] != nullptr) DT_PREFETCH(out.gp[k] + c * lv.plane + o[row][j], true);
        }
  }
}

// The backward of a prepared vector group of eight points e[0..8): as backward_point, eight at a time.
template <int CC, bool kBorder>
__attribute__((target("avx2,fma"))) void backward8(const BackGroup8& grp, const int64_t* e, int64_t Cdyn,
                                                   const std::vector<Level>& L, const std::vector<const float*>& lp,
                                                   const float* pg, const Grads<float>& out, int64_t gsc,
                                                   int64_t gsm, double border) {
  const int64_t C = CC > 0 ? CC : Cdyn;
  // The output gradient of each channel; points whose gradient is 0 in every channel write nothing (as
  // backward_point returns early: a zero weight times an infinite texel must not reach the uv gradient).
  // A run-time channel count's vectors live on the heap, 32-byte aligned by hand: std::vector<__m256> drops
  // the type's alignment (GCC ignores attributes on template arguments), and its 16-byte aligned storage
  // crashed the aligned stores for C = 5.
  constexpr int CMAX = CC > 0 ? CC : 1;
  std::vector<float> gheap(CC > 0 ? 0 : 8 * C + 7);
  __m256 gstack[CMAX];
  __m256* g = CC > 0 ? gstack
                     : reinterpret_cast<__m256*>((reinterpret_cast<uintptr_t>(gheap.data()) + 31) & ~uintptr_t{31});
  __m256 any = _mm256_setzero_ps();
  for (int64_t c = 0; c < C; ++c) {
    alignas(32) float gc[8];
    for (int j = 0; j < 8; ++j) gc[j] = pg[c * gsc + e[j] * gsm];
    g[c] = _mm256_load_ps(gc);
    any = _mm256_or_ps(any, _mm256_cmp_ps(g[c], _mm256_setzero_ps(), _CMP_NEQ_UQ));
  }
  const int live = _mm256_movemask_ps(any);
  if (live == 0) return;
  const __m256 bv = _mm256_set1_ps(static_cast<float>(border));
  __m256d du[2], dv[2], dD[2];
  for (int h = 0; h < 2; ++h) du[h] = dv[h] = dD[h] = _mm256_setzero_pd();
  std::vector<float> sheap(CC > 0 ? 0 : C * 32);
  alignas(32) float sstack[CMAX][4][8];
  float(*share)[4][8] = CC > 0 ? sstack : reinterpret_cast<float(*)[4][8]>(sheap.data());
  for (int jr = 0; jr < grp.r.n; ++jr) {
    const int64_t k = grp.r.k[jr];
    float* gk = out.gp[k];
    level_grads8<kBorder>(grp.lv[jr], L[k], lp[k], C, g, level_weight8(grp.r, jr), bv, grp.r.wt[jr], grp.r.dwt[jr],
                          gk != nullptr ? share : nullptr, du, dv, dD);
    if (gk == nullptr) continue;
    alignas(32) int32_t idx[4][8], in[4][8];
    for (int q = 0; q < 4; ++q) {
      _mm256_store_si256(reinterpret_cast<__m256i*>(idx[q]), grp.lv[jr].t.idx[q]);
      if (kBorder) _mm256_store_si256(reinterpret_cast<__m256i*>(in[q]), grp.lv[jr].t.in[q]);
    }
    // Point after point, its channels one after another: on a level a point or so apart, neighbouring points
    // add to the same texels, and each of those adds waits for the one before it to be stored; the other
    // channels' adds between the two fill the wait (measured against channel after channel, 1024^2 RGB
    // texture, 512^2 points, 2 threads: the trilinear step in 0.95-0.97x the time on a view of 2.6 texels a
    // pixel, whose levels 1 and 2 hold points 1.3 and 0.65 texels apart; 1.01x on one magnified to 0.65
    // texels a pixel). Each texel still gets its adds in the points' order.
    for (int j = 0; j < 8; ++j) {
      if (!(live >> j & 1)) continue;
      for (int64_t c = 0; c < C; ++c) {
        float* gq = gk + c * L[k].plane;
        for (int q = 0; q < 4; ++q)
          if (!kBorder || in[q][j]) gq[idx[q][j]] += share[c][q][j];
      }
    }
  }
  alignas(32) double ou[8], ov[8], oD[8];
  for (int h = 0; h < 2; ++h) {
    _mm256_store_pd(ou + 4 * h, du[h]);
    _mm256_store_pd(ov + 4 * h, dv[h]);
    _mm256_store_pd(oD + 4 * h, dD[h]);
  }
  for (int j = 0; j < 8; ++j) {
    if (!(live >> j & 1)) continue;
    if (out.uv) out.uv[2 * e[j]] = static_cast<float>(ou[j]), out.uv[2 * e[j] + 1] = static_cast<float>(ov[j]);
    if (out.D) out.D[e[j]] = static_cast<float>(oD[j]);
  }
}

// The backward of the points idx[0, n) by groups_of_eight, as many as fit (returned). Groups
// on mixed levels or holding a non-finite point go point by point through one, in their place in the order.
template <int CC, bool kBorder, typename One>
__attribute__((target("avx2,fma"))) int64_t backward_range8(const int64_t* idx, int64_t n, int64_t C,
                                                            const std::vector<Level>& L,
                                                            const std::vector<const float*>& lp, const float* puv,
                                                            const float* pd, const float* pg, const Grads<float>& out,
                                                            int64_t gsc, int64_t gsm, int64_t wrap_u, int64_t wrap_v,
                                                            double border, bool nearest, bool d_grad, One&& one) {
  const bool reads = out.uv != nullptr || out.D != nullptr;
  const int64_t end = n / 8 * 8;
  groups_of_eight<BackGroup8>(
      0, end,
      [&](int64_t s, BackGroup8& g) __attribute__((target("avx2,fma"))) {
        prepare_back8<CC>(idx + s, C, L, lp, puv, pd, pg, gsc, gsm, out, wrap_u, wrap_v, nearest, d_grad, reads, g);
      },
      [&](const BackGroup8& g, int64_t s) __attribute__((target("avx2,fma"))) {
        if (g.vec)
          backward8<CC, kBorder>(g, idx + s, C, L, lp, pg, out, gsc, gsm, border);
        else
          for (int j = 0; j < 8; ++j) one(idx[s + j]);
      });
  return end;
}

// Eight stochastic draws' backward (float32, points e[0..8) in the banded order): the draws and tap positions
// point by point (place_draw's), the taps of each drawn level placed in vectors (level8: the scalar
// placement's bits) and merged lane by lane into one set of offsets from the first level's texels where the
// two levels lie within int32 offsets of each other (prepare_draws8's merge); vec is false where a uv is not
// finite, the eight drew three levels or the offsets do not fit: those go through backward_draw.
struct BackDraw8 {
  bool vec;
  int64_t k[2];
  int32_t jr[8];          // each lane's level (0 or 1)
  Quad8 t[2];             // each level's taps (the scatter's offsets into that level's gradient)
  Quad8 m;                // the lanes' taps as offsets from lp[k[0]] (the gathers)
  __m256i plane;          // each lane's channel stride
  __m256 fx, fy, scale;
  __m256d sx[2], sy[2], w[2], h[2], wt[2], dscale[2];
};

// A merged offset (from the first level's texels) back to one on the lane's own level jr.
inline int32_t idx_of_level(int32_t merged, int32_t jr, int64_t diff) {
  return jr ? static_cast<int32_t>(merged - diff) : merged;
}

template <int CC>
DT_AVX2 void prepare_back_draws8(const int64_t* e, int64_t Cdyn, const std::vector<Level>& L,
                                 const std::vector<const float*>& lp, const float* puv, const float* pd,
                                 const Grads<float>& out, int64_t wrap_u, int64_t wrap_v, const ReadOptions& o,
                                 BackDraw8& g) {
  const int64_t C = CC > 0 ? CC : Cdyn;
  alignas(32) double u[8], v[8], wt[8], ds[8];
  alignas(32) float sc[8];
  int64_t kk[8];
  g.vec = false;
  const int64_t K = static_cast<int64_t>(L.size());
  for (int j = 0; j < 8; ++j) {  // place_draw's draw and tap position; the taps are placed in vectors below
    const int64_t p = e[j];
    const double pu = puv[2 * p], pv = puv[2 * p + 1];
    if (!std::isfinite(pu) || !std::isfinite(pv)) return;
    const Draw<float> dr = draw_of<float>(o, p, pd[p], K);
    kk[j] = dr.r.k[0];
    sc[j] = dr.scale;
    wt[j] = static_cast<double>(dr.scale);
    ds[j] = dr.dscale;
    u[j] = pu;
    v[j] = pv;
  }
  g.k[0] = g.k[1] = kk[0];
  for (int j = 1; j < 8; ++j) g.k[1] = kk[j] != kk[0] ? kk[j] : g.k[1];
  alignas(32) int32_t sel[8];
  for (int j = 0; j < 8; ++j) {
    if (kk[j] != g.k[0] && kk[j] != g.k[1]) return;
    g.jr[j] = kk[j] != g.k[0];
    sel[j] = -g.jr[j];
  }
  const int64_t diff = lp[g.k[1]] - lp[g.k[0]], p0 = L[g.k[0]].plane, p1 = L[g.k[1]].plane;
  const int64_t lo = std::min<int64_t>(0, diff), hi = std::max<int64_t>(C * p0, diff + C * p1);
  if (!(lo > -(int64_t(1) << 31) && hi < (int64_t(1) << 31))) return;
  Level8 a[2];
  level8(u, v, L[g.k[0]], wrap_u, wrap_v, a[0]);
  if (g.k[1] != g.k[0]) level8(u, v, L[g.k[1]], wrap_u, wrap_v, a[1]);
  else a[1] = a[0];
  const __m256i s = _mm256_load_si256(reinterpret_cast<const __m256i*>(sel));
  const __m256 sf = _mm256_castsi256_ps(s);
  const __m256i shift = _mm256_and_si256(s, _mm256_set1_epi32(static_cast<int32_t>(diff)));
  for (int q = 0; q < 4; ++q) {
    g.t[0].idx[q] = a[0].t.idx[q], g.t[1].idx[q] = a[1].t.idx[q];
    g.t[0].in[q] = a[0].t.in[q], g.t[1].in[q] = a[1].t.in[q];
    g.m.idx[q] = _mm256_add_epi32(_mm256_blendv_epi8(a[0].t.idx[q], a[1].t.idx[q], s), shift);
    g.m.in[q] = _mm256_blendv_epi8(a[0].t.in[q], a[1].t.in[q], s);
  }
  g.plane = _mm256_blendv_epi8(_mm256_set1_epi32(static_cast<int32_t>(p0)), _mm256_set1_epi32(static_cast<int32_t>(p1)), s);
  {  // the lines each point reads and writes: both rows of its tap, every channel
    alignas(32) int32_t r0[8], r1[8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(r0), g.m.idx[0]);
    _mm256_store_si256(reinterpret_cast<__m256i*>(r1), g.m.idx[2]);
    const float* base = lp[g.k[0]];
    for (int j = 0; j < 8; ++j) {
      const int64_t plane = L[kk[j]].plane;
      float* gk = out.gp[kk[j]];
      const int32_t a0 = idx_of_level(r0[j], g.jr[j], diff), a1 = idx_of_level(r1[j], g.jr[j], diff);
      for (int64_t c = 0; c < C; ++c) {
        DT_PREFETCH(base + r0[j] + c * plane, false);
        DT_PREFETCH(base + r1[j] + c * plane, false);
        if (gk != nullptr) {
          DT_PREFETCH(gk + a0 + c * plane, true);
          DT_PREFETCH(gk + a1 + c * plane, true);
        }
      }
    }
  }
  g.fx = _mm256_blendv_ps(a[0].fx, a[1].fx, sf);
  g.fy = _mm256_blendv_ps(a[0].fy, a[1].fy, sf);
  g.scale = _mm256_load_ps(sc);
  const double w0 = static_cast<double>(L[g.k[0]].w), w1 = static_cast<double>(L[g.k[1]].w);
  const double h0 = static_cast<double>(L[g.k[0]].h), h1 = static_cast<double>(L[g.k[1]].h);
  for (int hh = 0; hh < 2; ++hh) {
    alignas(32) int64_t mk[4];  // the lanes on the second level, as 64-bit masks
    for (int j = 0; j < 4; ++j) mk[j] = sel[4 * hh + j] ? -1 : 0;
    const __m256d md = _mm256_castsi256_pd(_mm256_load_si256(reinterpret_cast<const __m256i*>(mk)));
    g.sx[hh] = _mm256_blendv_pd(a[0].sx[hh], a[1].sx[hh], md);
    g.sy[hh] = _mm256_blendv_pd(a[0].sy[hh], a[1].sy[hh], md);
    g.w[hh] = _mm256_blendv_pd(_mm256_set1_pd(w0), _mm256_set1_pd(w1), md);
    g.h[hh] = _mm256_blendv_pd(_mm256_set1_pd(h0), _mm256_set1_pd(h1), md);
    g.wt[hh] = _mm256_load_pd(wt + 4 * hh);
    g.dscale[hh] = _mm256_load_pd(ds + 4 * hh);
  }
  g.vec = true;
}

// The backward of a prepared group: backward_draw's arithmetic lane by lane (the same bits), the texel
// gradients scattered point after point in the group's order, as backward_draw adds them.
template <int CC, bool kBorder>
__attribute__((target("avx2,fma"))) void backward_draws8(const BackDraw8& grp, const int64_t* e, int64_t Cdyn,
                                                         const std::vector<Level>& L,
                                                         const std::vector<const float*>& lp, const float* pg,
                                                         const Grads<float>& out, int64_t gsc, int64_t gsm,
                                                         double border) {
  const int64_t C = CC > 0 ? CC : Cdyn;
  constexpr int CMAX = CC > 0 ? CC : 1;
  std::vector<float> gheap(CC > 0 ? 0 : 8 * C + 7);
  __m256 gstack[CMAX];
  __m256* g = CC > 0 ? gstack
                     : reinterpret_cast<__m256*>((reinterpret_cast<uintptr_t>(gheap.data()) + 31) & ~uintptr_t{31});
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
  __m256 any = zero;
  for (int64_t c = 0; c < C; ++c) {
    alignas(32) float gc[8];
    for (int j = 0; j < 8; ++j) gc[j] = pg[c * gsc + e[j] * gsm];
    g[c] = _mm256_load_ps(gc);
    any = _mm256_or_ps(any, _mm256_cmp_ps(g[c], zero, _CMP_NEQ_UQ));
  }
  const int live = _mm256_movemask_ps(any);
  if (live == 0) return;
  const __m256 bv = _mm256_set1_ps(static_cast<float>(border));
  const __m256 fx = grp.fx, fy = grp.fy, gx = _mm256_sub_ps(one, fx), gy = _mm256_sub_ps(one, fy);
  const __m256 w[4] = {_mm256_mul_ps(gx, gy), _mm256_mul_ps(fx, gy), _mm256_mul_ps(gx, fy), _mm256_mul_ps(fx, fy)};
  const float* base = lp[grp.k[0]];
  std::vector<float> sheap(CC > 0 ? 0 : C * 32);
  alignas(32) float sstack[CMAX][4][8];
  float(*share)[4][8] = CC > 0 ? sstack : reinterpret_cast<float(*)[4][8]>(sheap.data());
  __m256 sx = zero, sy = zero, sv = zero;
  __m256i off = _mm256_setzero_si256();
  for (int64_t c = 0; c < C; ++c, off = _mm256_add_epi32(off, grp.plane)) {
    __m256 t[4];
    for (int q = 0; q < 4; ++q) {
      const __m256i idx = _mm256_add_epi32(grp.m.idx[q], off);
      t[q] = kBorder ? _mm256_mask_i32gather_ps(bv, base, idx, _mm256_castsi256_ps(grp.m.in[q]), 4)
                     : _mm256_i32gather_ps(base, idx, 4);
    }
    sx = _mm256_add_ps(sx, _mm256_mul_ps(g[c], _mm256_add_ps(_mm256_mul_ps(gy, _mm256_sub_ps(t[1], t[0])),
                                                             _mm256_mul_ps(fy, _mm256_sub_ps(t[3], t[2])))));
    sy = _mm256_add_ps(sy, _mm256_mul_ps(g[c], _mm256_add_ps(_mm256_mul_ps(gx, _mm256_sub_ps(t[2], t[0])),
                                                             _mm256_mul_ps(fx, _mm256_sub_ps(t[3], t[1])))));
    __m256 val = _mm256_add_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(w[0], t[0]), _mm256_mul_ps(w[1], t[1])),
                                             _mm256_mul_ps(w[2], t[2])), _mm256_mul_ps(w[3], t[3]));
    sv = _mm256_add_ps(sv, _mm256_mul_ps(g[c], val));
    const __m256 gw = _mm256_mul_ps(g[c], grp.scale);
    for (int q = 0; q < 4; ++q) _mm256_storeu_ps(share[c][q], _mm256_mul_ps(gw, w[q]));  // the heap: unaligned
  }
  alignas(32) int32_t idx[2][4][8], in[2][4][8];
  for (int jr = 0; jr < 2; ++jr)
    for (int q = 0; q < 4; ++q) {
      _mm256_store_si256(reinterpret_cast<__m256i*>(idx[jr][q]), grp.t[jr].idx[q]);
      if (kBorder) _mm256_store_si256(reinterpret_cast<__m256i*>(in[jr][q]), grp.t[jr].in[q]);
    }
  for (int j = 0; j < 8; ++j) {
    if (!(live >> j & 1)) continue;
    const int jr = grp.jr[j];
    float* gk = out.gp[grp.k[jr]];
    if (gk == nullptr) continue;
    const int64_t plane = L[grp.k[jr]].plane;
    for (int64_t c = 0; c < C; ++c) {
      float* gq = gk + c * plane;
      for (int q = 0; q < 4; ++q)
        if (!kBorder || in[jr][q][j]) gq[idx[jr][q][j]] += share[c][q][j];
    }
  }
  alignas(32) double ou[8], ov[8], oD[8];
  const __m256d zd = _mm256_setzero_pd();
  for (int hh = 0; hh < 2; ++hh) {
    const __m128 lo_x = hh == 0 ? _mm256_castps256_ps128(sx) : _mm256_extractf128_ps(sx, 1);
    const __m128 lo_y = hh == 0 ? _mm256_castps256_ps128(sy) : _mm256_extractf128_ps(sy, 1);
    const __m128 lo_v = hh == 0 ? _mm256_castps256_ps128(sv) : _mm256_extractf128_ps(sv, 1);
    const __m256d du = _mm256_add_pd(zd, _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(grp.wt[hh], _mm256_cvtps_pd(lo_x)),
                                                                     grp.sx[hh]), grp.w[hh]));
    const __m256d dv = _mm256_add_pd(zd, _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(grp.wt[hh], _mm256_cvtps_pd(lo_y)),
                                                                     grp.sy[hh]), grp.h[hh]));
    const __m256d dD = _mm256_add_pd(zd, _mm256_mul_pd(grp.dscale[hh], _mm256_cvtps_pd(lo_v)));
    _mm256_store_pd(ou + 4 * hh, _mm256_add_pd(zd, du));
    _mm256_store_pd(ov + 4 * hh, _mm256_add_pd(zd, dv));
    _mm256_store_pd(oD + 4 * hh, dD);
  }
  for (int j = 0; j < 8; ++j) {
    if (!(live >> j & 1)) continue;
    if (out.uv) out.uv[2 * e[j]] = static_cast<float>(ou[j]), out.uv[2 * e[j] + 1] = static_cast<float>(ov[j]);
    if (out.D) out.D[e[j]] = static_cast<float>(oD[j]);
  }
}

// The stochastic backward of the points idx[0, n) by groups_of_eight, as many as fit (returned); groups
// prepare_back_draws8 leaves to the scalar loop go point by point through one, in their place in the order.
template <int CC, bool kBorder, typename One>
__attribute__((target("avx2,fma"))) int64_t backward_draws_range8(
    const int64_t* idx, int64_t n, int64_t C, const std::vector<Level>& L, const std::vector<const float*>& lp,
    const float* puv, const float* pd, const float* pg, const Grads<float>& out, int64_t gsc, int64_t gsm,
    int64_t wrap_u, int64_t wrap_v, double border, const ReadOptions& opts, One&& one) {
  const int64_t end = n / 8 * 8;
  groups_of_eight<BackDraw8>(
      0, end,
      [&](int64_t s0, BackDraw8& g) __attribute__((target("avx2,fma"))) {
        prepare_back_draws8<CC>(idx + s0, C, L, lp, puv, pd, out, wrap_u, wrap_v, opts, g);
      },
      [&](const BackDraw8& g, int64_t s0) __attribute__((target("avx2,fma"))) {
        if (g.vec)
          backward_draws8<CC, kBorder>(g, idx + s0, C, L, lp, pg, out, gsc, gsm, border);
        else
          for (int j = 0; j < 8; ++j) one(idx[s0 + j]);
      });
  return end;
}

constexpr int64_t kMaxTaps8 = 16;  // the most taps a point of backward_taps8 (its held scatter: 16 KB at C = 4)

// The backward of eight points e[0..8) with N_j taps each (anisotropic, auto: count pc, axis pa; float32, the
// channel count fixed at compile time): as backward_point, eight at a time; false, with nothing written,
// where a coordinate is not finite, a point has more than kMaxTaps8 taps, or the eight read different
// levels. Tap i runs in the lanes with i < N_j (the others' sums are left as they are). The taps are placed,
// read and differentiated as the N-tap forward does them, and each
// point's level-gradient adds are held until all its taps are done, then made point by point in
// backward_point's order (tap, level, channel, texel): a texel's sum, and every other result, has the scalar
// loop's bits.
template <int CC, bool kBorder>
__attribute__((target("avx2,fma"))) bool backward_taps8(const int64_t* e, const std::vector<Level>& L,
                                                        const std::vector<const float*>& lp, const float* puv,
                                                        const float* pd, const int64_t* pc, const float* pa,
                                                        const float* pg, const Grads<float>& out, int64_t gsc,
                                                        int64_t gsm, int64_t wrap_u, int64_t wrap_v, double border,
                                                        bool nearest, bool d_grad) {
  static_assert(CC > 0, "the held scatter is sized at compile time");
  alignas(32) double u[8], v[8], au[8], av[8];
  alignas(32) int64_t N[8];
  alignas(32) float nfl[8];
  int64_t most = 0;
  for (int j = 0; j < 8; ++j) {
    u[j] = puv[2 * e[j]], v[j] = puv[2 * e[j] + 1];
    N[j] = tap_count(pc, e[j]);
    if (N[j] > kMaxTaps8 || !std::isfinite(u[j]) || !std::isfinite(v[j])) return false;
    au[j] = pa[2 * e[j]], av[j] = pa[2 * e[j] + 1];
    nfl[j] = static_cast<float>(N[j]);
    most = std::max(most, N[j]);
  }
  Reads8 r;
  if (!reads8(pd, e, static_cast<int64_t>(L.size()), nearest, d_grad, &r)) return false;
  // Each tap's share of the output gradient; points whose share is 0 in every channel write nothing.
  __m256 g[CC];
  __m256 any = _mm256_setzero_ps();
  const __m256 nf = _mm256_load_ps(nfl);
  for (int c = 0; c < CC; ++c) {
    alignas(32) float gc[8];
    for (int j = 0; j < 8; ++j) gc[j] = pg[c * gsc + e[j] * gsm];
    g[c] = _mm256_div_ps(_mm256_load_ps(gc), nf);
    any = _mm256_or_ps(any, _mm256_cmp_ps(g[c], _mm256_setzero_ps(), _CMP_NEQ_UQ));
  }
  const int live = _mm256_movemask_ps(any);
  if (live == 0) return true;
  const int n = r.n;
  __m256 wl[2];
  for (int jr = 0; jr < n; ++jr) wl[jr] = level_weight8(r, jr);
  const __m256 bv = _mm256_set1_ps(static_cast<float>(border));
  const __m256d zero = _mm256_setzero_pd();
  __m256d du[2], dv[2], dD[2], dax[2], day[2];
  for (int h = 0; h < 2; ++h) du[h] = dv[h] = dD[h] = dax[h] = day[h] = zero;
  alignas(32) int32_t idx[kMaxTaps8][2][4][8], in[kMaxTaps8][2][4][8];
  alignas(32) float share[kMaxTaps8][2][CC][4][8];
  const TapLine8 line(u, v, au, av, N);
  for (int64_t i = 0; i < most; ++i) {
    alignas(32) double tu[8], tv[8];
    __m256d o[2], mask[2];  // mask: the lanes with a tap i, all ones
    line.place(i, tu, tv, o);
    line.on_pd(i, mask);
    __m256d tdu[2] = {zero, zero}, tdv[2] = {zero, zero};
    for (int jr = 0; jr < n; ++jr) {
      const int64_t k = r.k[jr];
      const bool held = out.gp[k] != nullptr;
      Level8 a;
      level8(tu, tv, L[k], wrap_u, wrap_v, a);
      level_grads8<kBorder>(a, L[k], lp[k], CC, g, wl[jr], bv, r.wt[jr], r.dwt[jr], held ? share[i][jr] : nullptr, tdu,
                            tdv, dD, mask);
      if (held)
        for (int q = 0; q < 4; ++q) {
          _mm256_store_si256(reinterpret_cast<__m256i*>(idx[i][jr][q]), a.t.idx[q]);
          if (kBorder) _mm256_store_si256(reinterpret_cast<__m256i*>(in[i][jr][q]), a.t.in[q]);
        }
    }
    for (int h = 0; h < 2; ++h) {
      du[h] = _mm256_blendv_pd(du[h], _mm256_add_pd(du[h], tdu[h]), mask[h]);
      dv[h] = _mm256_blendv_pd(dv[h], _mm256_add_pd(dv[h], tdv[h]), mask[h]);
      dax[h] = _mm256_blendv_pd(dax[h], _mm256_add_pd(dax[h], _mm256_mul_pd(o[h], tdu[h])), mask[h]);
      day[h] = _mm256_blendv_pd(day[h], _mm256_add_pd(day[h], _mm256_mul_pd(o[h], tdv[h])), mask[h]);
    }
  }
  for (int j = 0; j < 8; ++j) {
    if (!(live >> j & 1)) continue;
    for (int64_t i = 0; i < N[j]; ++i)
      for (int jr = 0; jr < n; ++jr) {
        float* gk = out.gp[r.k[jr]];
        if (gk == nullptr) continue;
        const int64_t plane = L[r.k[jr]].plane;
        for (int c = 0; c < CC; ++c)
          for (int q = 0; q < 4; ++q)
            if (!kBorder || in[i][jr][q][j]) gk[c * plane + idx[i][jr][q][j]] += share[i][jr][c][q][j];
      }
  }
  alignas(32) double res[5][8];
  for (int h = 0; h < 2; ++h) {
    _mm256_store_pd(res[0] + 4 * h, du[h]);
    _mm256_store_pd(res[1] + 4 * h, dv[h]);
    _mm256_store_pd(res[2] + 4 * h, dD[h]);
    _mm256_store_pd(res[3] + 4 * h, dax[h]);
    _mm256_store_pd(res[4] + 4 * h, day[h]);
  }
  for (int j = 0; j < 8; ++j) {
    if (!(live >> j & 1)) continue;
    if (out.uv) out.uv[2 * e[j]] = static_cast<float>(res[0][j]), out.uv[2 * e[j] + 1] = static_cast<float>(res[1][j]);
    if (out.D) out.D[e[j]] = static_cast<float>(res[2][j]);
    if (out.axis) out.axis[2 * e[j]] = static_cast<float>(res[3][j]), out.axis[2 * e[j] + 1] = static_cast<float>(res[4][j]);
  }
  return true;
}
#endif

#if DT_HAVE_AVX2
// tap_key of the points [lo, hi) (float32; one tap each, or count pc along axis pa), four at a time in
// double, for wrap_v repeat, clamp or border: where a point is finite, its taps' v range [v - r, v + r]
// (r = |a_v| (1/2 - 1/(2N)), 0 for one tap) lies within |v| < 2^31 (and within a period for repeat) and its
// rows fit a scale's bands, the key is tap_key's (the same double arithmetic: rows floor(lo h - 0.5) - 1 ..
// floor(hi h - 0.5) + 2 on each level read, the band floor(a nb / h), exact as every product is an integer
// under 2^53, at the finest scale that holds the rows) and its levels are marked in rd; the other points go
// to key_of. Measured: tap_key one point at a time was 13 % of a one-thread trilinear forward+backward,
// this 3.7 %.
// (Templated on the pointers' type, as the float64 instantiation of the caller names it too; only float runs.)
template <typename S, typename KeyOf>
__attribute__((target("avx2,fma"))) void tap_keys4(int64_t lo, int64_t hi, const S* puv_s, const S* pd_s,
                                                   const int64_t* pc, const S* pa_s, const double* hd, int64_t K,
                                                   bool nearest, bool d_grad, int wrap_v, const ScaleBands& T,
                                                   int32_t* keys, char* rd, KeyOf key_of) {
  const __m256d zero = _mm256_setzero_pd(), one = _mm256_set1_pd(1.0), half = _mm256_set1_pd(0.5);
  const __m256d top = _mm256_set1_pd(static_cast<double>(K - 1)), big = _mm256_set1_pd(2147483648.0);
  const __m256d two = _mm256_set1_pd(2.0), abs_mask = _mm256_castsi256_pd(_mm256_set1_epi64x(INT64_MAX));
  const __m256i deal = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
  const bool repeat = wrap_v == REPEAT;
  const float *puv = reinterpret_cast<const float*>(puv_s), *pd = reinterpret_cast<const float*>(pd_s);
  const float* pa = reinterpret_cast<const float*>(pa_s);
  int64_t e = lo;
  for (; e + 4 <= hi; e += 4) {
    const __m256 uv = _mm256_permutevar8x32_ps(_mm256_loadu_ps(puv + 2 * e), deal);
    const __m256d u = _mm256_cvtps_pd(_mm256_castps256_ps128(uv)), v0 = _mm256_cvtps_pd(_mm256_extractf128_ps(uv, 1));
    const __m256d d = _mm256_cvtps_pd(_mm_loadu_ps(pd + e));
    // finite u, v, d and |v| < 2^31
    __m256d ok = _mm256_cmp_pd(_mm256_add_pd(_mm256_sub_pd(u, u), _mm256_sub_pd(d, d)), zero, _CMP_EQ_OQ);
    ok = _mm256_and_pd(ok, _mm256_cmp_pd(_mm256_and_pd(v0, abs_mask), big, _CMP_LT_OQ));
    // reads_of: the levels k0, k1 (k1 = k0 where one level is read)
    __m256d k0, k1;
    if (nearest) {
      k0 = k1 = _mm256_min_pd(_mm256_max_pd(_mm256_floor_pd(_mm256_add_pd(d, half)), zero), top);
    } else {
      k0 = _mm256_min_pd(_mm256_max_pd(_mm256_floor_pd(d), zero), top);
      const __m256d t = _mm256_sub_pd(d, k0);
      const __m256d both = _mm256_and_pd(_mm256_cmp_pd(k0, top, _CMP_LT_OQ), _mm256_cmp_pd(t, zero, _CMP_GT_OQ));
      k1 = _mm256_blendv_pd(k0, _mm256_add_pd(k0, one), both);
      if (d_grad) {
        const __m256d below = _mm256_andnot_pd(both, _mm256_cmp_pd(k0, zero, _CMP_GT_OQ));
        k1 = _mm256_blendv_pd(k1, _mm256_sub_pd(k0, one), below);
      }
    }
    const __m128i i0 = _mm256_cvttpd_epi32(k0), i1 = _mm256_cvttpd_epi32(k1);
    const __m256d h0 = _mm256_i32gather_pd(hd, i0, 8), h1 = _mm256_i32gather_pd(hd, i1, 8);
    // The taps' v range [vl, vh] as tap_key computes it: v -+ r, then (repeat) both less floor(v).
    __m256d vl = v0, vh = v0;
    if (pc != nullptr) {
      const __m256d n = _mm256_setr_pd(static_cast<double>(pc[e]), static_cast<double>(pc[e + 1]),
                                       static_cast<double>(pc[e + 2]), static_cast<double>(pc[e + 3]));
      const __m256d av = _mm256_cvtps_pd(_mm256_extractf128_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(pa + 2 * e),
                                                                                        deal), 1));
      __m256d r = _mm256_mul_pd(_mm256_and_pd(av, abs_mask), _mm256_sub_pd(half, _mm256_div_pd(half, n)));
      r = _mm256_and_pd(r, _mm256_cmp_pd(n, one, _CMP_GT_OQ));  // one tap (N <= 1): 0
      vl = _mm256_sub_pd(v0, r);
      vh = _mm256_add_pd(v0, r);
      // finite, |vl|, |vh| < 2^31 (NaN fails), and within a period for repeat
      ok = _mm256_and_pd(ok, _mm256_and_pd(_mm256_cmp_pd(_mm256_and_pd(vl, abs_mask), big, _CMP_LT_OQ),
                                           _mm256_cmp_pd(_mm256_and_pd(vh, abs_mask), big, _CMP_LT_OQ)));
      if (repeat) ok = _mm256_and_pd(ok, _mm256_cmp_pd(_mm256_sub_pd(vh, vl), one, _CMP_LT_OQ));
    }
    if (repeat) {
      const __m256d s = _mm256_floor_pd(v0);
      vl = _mm256_sub_pd(vl, s);
      vh = _mm256_sub_pd(vh, s);
    }
    // rows_of: a = floor(vl h - 0.5) - 1, b = floor(vh h - 0.5) + 2, clamped to [0, h - 1] but for repeat
    __m256d a0 = _mm256_sub_pd(_mm256_floor_pd(_mm256_sub_pd(_mm256_mul_pd(vl, h0), half)), one);
    __m256d a1 = _mm256_sub_pd(_mm256_floor_pd(_mm256_sub_pd(_mm256_mul_pd(vl, h1), half)), one);
    __m256d b0 = _mm256_add_pd(_mm256_floor_pd(_mm256_sub_pd(_mm256_mul_pd(vh, h0), half)), two);
    __m256d b1 = _mm256_add_pd(_mm256_floor_pd(_mm256_sub_pd(_mm256_mul_pd(vh, h1), half)), two);
    if (!repeat) {
      const __m256d l0 = _mm256_sub_pd(h0, one), l1 = _mm256_sub_pd(h1, one);
      a0 = _mm256_min_pd(_mm256_max_pd(a0, zero), l0); b0 = _mm256_min_pd(_mm256_max_pd(b0, zero), l0);
      a1 = _mm256_min_pd(_mm256_max_pd(a1, zero), l1); b1 = _mm256_min_pd(_mm256_max_pd(b1, zero), l1);
    }
    // The finest scale whose bands hold the rows (tap_key's loop over scales, for the lanes left each time).
    __m256d pending = ok, key = zero;
    const __m256d e0 = _mm256_add_pd(b0, one), e1 = _mm256_add_pd(b1, one);
    double nbs = static_cast<double>(T.nb0);
    // The finest scale's bands, floor(a nb0 / h) (exact: the quotient is under 2^11, the nearest double to it
    // is an integer only where it is one); a coarser scale's band is floor(that / 2^s), exactly the same as
    // floor(a (nb0 / 2^s) / h), so the loop needs no division (measured, in one process with and without:
    // the trilinear step 0.985x).
    const __m256d nb0 = _mm256_set1_pd(nbs);
    const __m256d fine = _mm256_min_pd(_mm256_floor_pd(_mm256_div_pd(_mm256_mul_pd(a0, nb0), h0)),
                                       _mm256_floor_pd(_mm256_div_pd(_mm256_mul_pd(a1, nb0), h1)));
    for (int64_t sc = 0; sc < T.scales && _mm256_movemask_pd(pending); ++sc, nbs *= 0.5) {
      const __m256d nb = _mm256_set1_pd(nbs);
      const __m256d band = _mm256_floor_pd(_mm256_mul_pd(fine, _mm256_set1_pd(nbs / static_cast<double>(T.nb0))));
      const __m256d room = _mm256_add_pd(band, two);
      const __m256d fits = _mm256_and_pd(_mm256_cmp_pd(_mm256_mul_pd(e0, nb), _mm256_mul_pd(room, h0), _CMP_LE_OQ),
                                         _mm256_cmp_pd(_mm256_mul_pd(e1, nb), _mm256_mul_pd(room, h1), _CMP_LE_OQ));
      // band mod nb (a power of two: the quotient is exact), plus the scale's first key
      const __m256d wrapped =
          _mm256_sub_pd(band, _mm256_mul_pd(nb, _mm256_floor_pd(_mm256_mul_pd(band, _mm256_set1_pd(1.0 / nbs)))));
      key = _mm256_blendv_pd(key, _mm256_add_pd(wrapped, _mm256_set1_pd(static_cast<double>(T.offset[sc]))),
                             _mm256_and_pd(pending, fits));
      pending = _mm256_andnot_pd(fits, pending);
    }
    ok = _mm256_andnot_pd(pending, ok);
    alignas(16) int32_t kk[4], l0[4], l1[4];
    _mm_store_si128(reinterpret_cast<__m128i*>(kk), _mm256_cvttpd_epi32(key));
    _mm_store_si128(reinterpret_cast<__m128i*>(l0), i0);
    _mm_store_si128(reinterpret_cast<__m128i*>(l1), i1);
    const int live = _mm256_movemask_pd(ok);
    for (int j = 0; j < 4; ++j) {
      if (live >> j & 1) {
        keys[e + j] = kk[j];
        rd[l0[j]] = 1;
        rd[l1[j]] = 1;
      } else {
        keys[e + j] = key_of(e + j, rd);
      }
    }
  }
  for (; e < hi; ++e) keys[e] = key_of(e, rd);
}
#endif

}  // namespace

std::tuple<std::vector<Tensor>, Tensor, Tensor, Tensor> backward(
    std::vector<Tensor> levels, Tensor uv, Tensor D, Tensor axis, Tensor count,
    Tensor grad, const ReadOptions& opts, const TapNeeds& need) {
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
  DT_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == uv.scalar_type(),
              "mip_read: grad must be [C, M] of uv's dtype");
  const int64_t gsc = grad.stride(0), gsm = grad.stride(1);
  need_axis = need_axis && count.numel();
  std::vector<Tensor> gl(K);
  Tensor guv = need_uv ? zeros({M, 2}, options_of(uv)) : Tensor();
  Tensor gD = need_D ? zeros({M}, options_of(uv)) : Tensor();
  Tensor gax = need_axis ? zeros({M, 2}, options_of(uv)) : Tensor();
  DT_CHECK(!opts.stochastic || count.numel() == 0, "mip_read: a stochastic draw takes no counts");
  const bool sto = opts.stochastic;  // backward_draw(s8) (why: forward)
  const bool sto_simd = sto && simd_levels(uv, levels);
  const bool simd = !sto && simd_taps(uv, count, levels);
  const bool simd_n = !sto && simd_levels(uv, levels) && count.numel() != 0;
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "mip_read_backward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.mutable_data_ptr<scalar_t>());
    Grads<scalar_t> out;
    out.gp.assign(K, nullptr);
    out.uv = need_uv ? guv.mutable_data_ptr<scalar_t>() : nullptr;
    out.D = need_D ? gD.mutable_data_ptr<scalar_t>() : nullptr;
    out.axis = need_axis ? gax.mutable_data_ptr<scalar_t>() : nullptr;
    const int64_t* pc = count.numel() ? count.mutable_data_ptr<int64_t>() : nullptr;
    const scalar_t* pa = pc ? axis.mutable_data_ptr<scalar_t>() : nullptr;
    const scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *pd = D.mutable_data_ptr<scalar_t>(), *pg = grad.mutable_data_ptr<scalar_t>();
    std::vector<int32_t> keys;
    ScaleBands bands;
    if (need_levels) {
      // The points' band keys, and the levels read (their gradients are allocated, zeroed, only for those).
      bands = scale_bands(L[0].h);
      std::vector<double> inv_h(K);
      for (int64_t k = 0; k < K; ++k) inv_h[k] = 1.0 / static_cast<double>(L[k].h);
      // A stochastic draw writes rows of one of the levels the deterministic filter reads (floor(D) or
      // floor(D) + 1): the deterministic key covers them, and costs no draw (measured: drawing each point
      // again for its key was as long as its backward).
      auto key_of = [&](int64_t e, char* rd) {
        const Reads r = reads_of(static_cast<double>(pd[e]), K, nearest, d_grad);
        const int64_t N = tap_count(pc, e);
        const int32_t key = tap_key(bands, L, inv_h.data(), puv[2 * e], puv[2 * e + 1], r, N,
                                    pc ? static_cast<double>(pa[2 * e + 1]) : 0.0, static_cast<int>(wrap_v));
        if (key >= 0)
          for (int j = 0; j < r.n; ++j) rd[r.k[j]] = 1;
        return key;
      };
      std::vector<char> read;
#if DT_HAVE_AVX2
      if constexpr (std::is_same_v<scalar_t, float>) {
        if ((simd || simd_n || sto_simd) && wrap_v != MIRROR && bands.scales > 0) {
          std::vector<double> hd(K);
          for (int64_t k = 0; k < K; ++k) hd[k] = static_cast<double>(L[k].h);
          read = band_key_ranges(M, K, keys, [&](int64_t lo, int64_t hi, int32_t* out, char* rd) {
            tap_keys4(lo, hi, puv, pd, pc, pa, hd.data(), K, nearest, d_grad, static_cast<int>(wrap_v), bands, out,
                      rd, key_of);
          });
        }
      }
#endif
      if (read.empty()) read = band_keys(M, K, keys, key_of);
      for (int64_t k = 0; k < K; ++k) {
        if (!read[k]) continue;
        gl[k] = zeros_like(levels[k]);
        out.gp[k] = gl[k].template mutable_data_ptr<scalar_t>();
      }
    }
    specialized(C, wrap_u, wrap_v, [&](auto cc, auto border_) {
      constexpr int CC = decltype(cc)::value;
      constexpr bool kB = decltype(border_)::value;
      auto one = [&](int64_t e) {
        backward_point<scalar_t, CC, kB>(e, C, L, lp, puv, pd, pc, pa, pg, out, gsc, gsm, wrap_u, wrap_v, border,
                                         nearest, d_grad);
      };
      // The points idx[0, n): by eight where the eight-point path takes them, else one at a time.
      auto run = [&](const int64_t* idx, int64_t n) {
#if DT_HAVE_AVX2
        if constexpr (std::is_same_v<scalar_t, float>) {
          if (sto_simd) {
            auto one_draw = [&](int64_t e) {
              Placed<scalar_t> q;
              place_draw(opts, e, L, puv, pd, wrap_u, wrap_v, q);
              backward_draw<scalar_t, CC, kB>(q, e, C, L, lp, pg, out, gsc, gsm, border);
            };
            const int64_t end = backward_draws_range8<CC, kB>(idx, n, C, L, lp, puv, pd, pg, out, gsc, gsm, wrap_u,
                                                              wrap_v, border, opts, one_draw);
            for (int64_t i = end; i < n; ++i) one_draw(idx[i]);
            return;
          }
        }
#endif
        if (sto) {  // placed a block ahead and prefetched (forward_draws)
          Placed<scalar_t> blk[2][kDrawBlock];
          auto fill = [&](int64_t i0, Placed<scalar_t>* q) {
            const int64_t m = std::min<int64_t>(kDrawBlock, n - i0);
            for (int64_t i = 0; i < m; ++i) {
              place_draw(opts, idx[i0 + i], L, puv, pd, wrap_u, wrap_v, q[i]);
              prefetch_draw<scalar_t>(q[i], C, L, lp, out.gp.data());
            }
            return m;
          };
          int cur = 0;
          int64_t m = n > 0 ? fill(0, blk[0]) : 0;
          for (int64_t i0 = 0; m > 0; i0 += kDrawBlock, cur ^= 1) {
            const int64_t next = i0 + kDrawBlock < n ? fill(i0 + kDrawBlock, blk[cur ^ 1]) : 0;
            for (int64_t i = 0; i < m; ++i)
              backward_draw<scalar_t, CC, kB>(blk[cur][i], idx[i0 + i], C, L, lp, pg, out, gsc, gsm, border);
            m = next;
          }
          return;
        }
        int64_t i = 0;
#if DT_HAVE_AVX2
        if constexpr (std::is_same_v<scalar_t, float>) {
          if (simd) i = backward_range8<CC, kB>(idx, n, C, L, lp, puv, pd, pg, out, gsc, gsm, wrap_u, wrap_v, border,
                                                nearest, d_grad, one);
          if constexpr (CC > 0) {
            for (; simd_n && i + 8 <= n; i += 8)
              if (!backward_taps8<CC, kB>(idx + i, L, lp, puv, pd, pc, pa, pg, out, gsc, gsm, wrap_u, wrap_v, border,
                                          nearest, d_grad))
                for (int j = 0; j < 8; ++j) one(idx[i + j]);
          }
        }
#endif
        for (; i < n; ++i) one(idx[i]);
      };
      if (need_levels) {
        run_banded(keys.data(), M, bands.classes, run);
      } else {  // no scatter: the points are independent
        parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
          std::vector<int64_t> idx(hi - lo);
          for (int64_t e = lo; e < hi; ++e) idx[e - lo] = e;
          run(idx.data(), hi - lo);
        });
      }
    });
  });
  return {gl, guv, gD, gax};
}

}  // namespace difftex
