// The visibility pass of difftex.rasterize on the CPU (geometry/raster.py
// _visibility, whose torch path stays the tested reference): per pixel the
// id of the nearest covering triangle and its float64 NDC depth. The same
// rules and the same floating-point operations in the same order as the
// torch path, so both give identical ids:
//   * triangles whose three corners have w > 0 and project inside the guard
//     band are snapped to a fixed-point grid (2^bits units a pixel, origin
//     at the image centre, rows growing downwards) and tested with exact
//     int64 edge functions and the top-left rule (a centre on an edge
//     belongs to the triangle it enters when nudged by (d, d^2), d -> 0+):
//     watertight, each centre inside exactly one triangle of a closed fan;
//   * the others (a corner at w <= 0 or far off screen) take float64 2D
//     homogeneous edge functions (Olano & Greer 1997) of per-vertex
//     power-of-two-scaled clip coordinates;
//   * the depth is the float64 NDC z of the unsnapped triangle's plane at
//     the pixel centre, kept where -1 <= z <= 1; nearest wins, a tie goes to
//     the lowest face id; with a floor (depth peeling) only fragments behind
//     the floor's (depth, id) in that order count.
// Passes: the vertices (outcode, snap; finiteness), the triangles in chunks
// (index range, culling, the box of pixel centres and, for boxes of a few
// centres, whether one is covered: a dense mesh's many triangles that
// cover no centre stop here), the survivors binned into bands of 8 rows in
// increasing id, then the bands, handed out one at a time to the threads,
// each rasterized by one thread into its own rows (no races, the result
// does not depend on the thread count or the order). Where the CPU has
// AVX2 (and set_simd leaves it on), the vertex pass takes four vertices at
// a time and the triangle pass eight triangles (dropped8): the same
// decisions on exact values, and the small triangles it finds covering
// centres are listed with those centres, so that their bands only set up
// the depth plane. On icosphere(8) at 512^2 (1.3M triangles of ~0.2 px),
// one thread: vertices 8 -> 4 ms, triangles 43 -> 24, bands 18 -> 9. Each
// band resolves its z-buffer in a per-thread buffer in cache and writes its
// rows out once at the end (clearing the outputs first was a second pass
// over them and took their page faults where the allocator had handed the
// memory back: 40 % of the bands' cycles on spot at 512^2, one thread, in
// an rdtsc profile on a loaded machine); in plain mode
// (rasterize: one layer, no floor, no count) the exact path's rows then
// take four centres at a time (exact_row_avx2, same decisions).
// raster_fused (rasterize's one call on the CPU) hands each band, once its
// ids are written, to raster_fragments' row code (FragRows) on the same
// thread, while the band's ids and triangles are in cache: one parallel
// region, no second pass over the ids, no depth buffer written out.
#include "common.h"
#include "kernels.h"

#include "stable.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <type_traits>
#include <vector>

#if DT_HAVE_AVX2
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace difftex {
namespace {

constexpr double kGuard = 536870912.0;  // 2^29: geometry/raster.py _GUARD
constexpr int64_t kEmpty = std::numeric_limits<int64_t>::max();
constexpr int64_t kBand = 8;  // rows a band

// A triangle that covers something: its id (with kFloatBit set where it
// takes the float path), the bands of rows it touches, and for the exact
// path its corners' ids and snapped positions, so that the bands (which
// list pointers to these records) read no face row and no corner record:
// only the corners' positions for the depth plane.
struct Live {
  int32_t f, band0, band1;
  int32_t v[3], x[3], y[3];
};
constexpr int32_t kFloatBit = int32_t(1) << 30;
// x[2] of a record whose coverage the triangle pass found (the eight-
// triangle filter: a box of at most kProbe centres): x[0], y[0] the box's
// first column and row, x[1] its columns, y[1] the covered centre slots
// (bit s: slot s, as dropped8 numbers them); no snapped corner is there.
constexpr int32_t kDirect = std::numeric_limits<int32_t>::min();

// Per vertex, what the per-triangle pass over a big mesh reads, in one
// 12-byte record (one cache line a corner: the corners of a dense mesh are
// scattered, so the pass is bound by these misses): the snapped position
// (|q| <= 2^29 fits int32) and the outcode (bit 7: snapped). The NDC of the
// depth plane and the float path's scale are recomputed from pos for the
// few triangles that survive the coverage test (writing them per vertex
// cost more than that).
constexpr uint8_t kSnapped = 0x80;

struct Vert {
  int32_t x, y;
  uint8_t code;
};

struct Exact {
  int64_t x[3], y[3];
  int64_t a[3], b[3], c[3], thr[3];
  double z0, x0, y0, zx, zy;
  int64_t c0, c1, r0, r1;
};

// 2^-e where frexp(m) = f 2^e (f in [0.5, 1)): the float path's scale of a
// vertex whose largest |coordinate| is m >= 0, from the exponent bits (the
// libm frexp / ldexp calls cost more than the rest of the vertex pass);
// zero, subnormal, non-finite or huge m take the libm route. A subnormal m
// gets the largest finite factor instead (2^1023), which brings it into
// [2^-51, 2): no overflow, no inf.
inline double pow2_scale(double m) {
  uint64_t bits;
  std::memcpy(&bits, &m, 8);
  const int be = int(bits >> 52) & 0x7ff;
  const int rb = 2045 - be;  // biased exponent of 2^-(be - 1022)
  if (be == 0 || be == 0x7ff || rb <= 0) {
    int ex = 0;
    std::frexp(m, &ex);
    return std::ldexp(1.0, std::min(-ex, 1023));  // subnormal m: 2^-ex would overflow; scale as far as it goes
  }
  const uint64_t r = uint64_t(rb) << 52;
  double out;
  std::memcpy(&out, &r, 8);
  return out;
}

// The corners of a dense mesh are scattered in memory: both triangle
// loops ask for the corner records of the triangle kAhead places on, so
// that their cache misses overlap instead of stalling one by one.
constexpr int64_t kAhead = 8;

inline double max_abs4(const double* p) {
  return std::max({std::abs(p[0]), std::abs(p[1]), std::abs(p[2]), std::abs(p[3])});
}

// nearbyint in the default rounding mode (to nearest, ties to even) for
// |v| <= 2^51: adding 1.5 * 2^52 leaves no fraction bits (an inline add
// where the baseline x86-64 target calls libm's nearbyint).
inline double round_even(double v) {
  constexpr double kMagic = 6755399441055744.0;
  return (v + kMagic) - kMagic;
}

struct Float {
  double a[3], b[3], c[3], thr[3], zc[3];
  int64_t c0, c1, r0, r1;
};

// Work items [0, n) handed out one at a time to the threads of one
// parallel_for region (its static split into equal ranges left one
// thread idle while the other drew the rows where the mesh is): run(next)
// is called once per thread with a function giving the next item, or -1.
// Which thread does an item does not change the result: each item owns its
// output.
template <typename Run>
void dynamic_for(int64_t n, Run&& run) {
  std::atomic<int64_t> counter{0};
  const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(get_num_threads(), n));
  parallel_for(0, threads, 1, [&](int64_t lo, int64_t hi) {
    auto next = [&]() -> int64_t {
      const int64_t i = counter.fetch_add(1, std::memory_order_relaxed);
      return i < n ? i : -1;
    };
    for (int64_t t = lo; t < hi; ++t) run(next);
  });
}

inline int64_t floor_div(int64_t a, int64_t d) { return a >= 0 ? a / d : -((-a + d - 1) / d); }

// The columns i in [lo, hi] of a row where all three exact edge functions
// E_k + s_k i reach their thresholds thr_k (E affine in the column): each
// edge bounds i from one side, solved exactly; lo > hi where none is inside.
template <typename Thr>
inline void row_span(int64_t E0, int64_t E1, int64_t E2, int64_t s0, int64_t s1, int64_t s2, const Thr& thr,
                     int64_t& lo, int64_t& hi) {
  const int64_t Es[3] = {E0, E1, E2}, ss[3] = {s0, s1, s2};
  for (int k = 0; k < 3 && lo <= hi; ++k) {
    const int64_t d = Es[k] - thr[k];  // inside where d + ss[k] * i >= 0
    if (ss[k] > 0)
      lo = std::max(lo, -floor_div(d, ss[k]));
    else if (ss[k] < 0)
      hi = std::min(hi, floor_div(d, -ss[k]));
    else if (d < 0)
      hi = -1;
  }
}

struct Ctx {
  const void* pos;  // [V, 4] of this batch item, float64 or (f32) float32
  bool f32;
  const int64_t* faces;
  const Vert* vert;
  int64_t H, W, S;
  bool cull;

  // Vertex v's clip coordinates, exactly, as float64 (float32 input is
  // read as it is: no converted copy of a big mesh's positions).
  void corner(int64_t v, double* p) const {
    if (f32) {
      const float* q = static_cast<const float*>(pos) + 4 * v;
      for (int i = 0; i < 4; ++i) p[i] = q[i];
    } else {
      const double* q = static_cast<const double*>(pos) + 4 * v;
      for (int i = 0; i < 4; ++i) p[i] = q[i];
    }
  }
  const char* row(int64_t v) const { return static_cast<const char*>(pos) + (f32 ? 16 : 32) * v; }
};

// Exact-path setup (raster.py _prepare_exact) in three steps, each false
// where the triangle covers nothing. exact_box: the snapped corners and the
// box of pixel centres they span, all integer, no division: most triangles
// of a dense mesh hold no centre and stop here.
inline bool exact_box(const Ctx& cx, Exact& t) {
  // Floor / ceiling division by 2h = 2^S as arithmetic shifts (an int64
  // idiv per side cost more than the rest of the test).
  const int64_t h = int64_t(1) << (cx.S - 1);
  const int64_t xmin = std::min({t.x[0], t.x[1], t.x[2]}), xmax = std::max({t.x[0], t.x[1], t.x[2]});
  const int64_t ymin = std::min({t.y[0], t.y[1], t.y[2]}), ymax = std::max({t.y[0], t.y[1], t.y[2]});
  t.c0 = std::max<int64_t>(0, -((-(xmin + (cx.W - 1) * h)) >> cx.S));
  t.c1 = std::min<int64_t>(cx.W - 1, (xmax + (cx.W - 1) * h) >> cx.S);
  t.r0 = std::max<int64_t>(0, -((-(ymin + (cx.H - 1) * h)) >> cx.S));
  t.r1 = std::min<int64_t>(cx.H - 1, (ymax + (cx.H - 1) * h) >> cx.S);
  return t.c0 <= t.c1 && t.r0 <= t.r1;
}

// The same, loading the snapped corners of triangle f first.
inline bool exact_box(const Ctx& cx, int64_t f, Exact& t) {
  const int64_t* fv = cx.faces + 3 * f;
  for (int i = 0; i < 3; ++i) {
    const Vert& v = cx.vert[fv[i]];
    t.x[i] = v.x;
    t.y[i] = v.y;
  }
  return exact_box(cx, t);
}

// exact_edges (after exact_box): the edge functions oriented so that the
// inside is >= thr (the top-left rule), culling and degeneracy.
inline bool exact_edges(const Ctx& cx, Exact& t) {
  for (int i = 0; i < 3; ++i) {
    const int j = (i + 1) % 3, k = (i + 2) % 3;
    t.a[i] = t.y[k] - t.y[j];
    t.b[i] = t.x[j] - t.x[k];
    t.c[i] = -(t.a[i] * t.x[j] + t.b[i] * t.y[j]);
  }
  const int64_t area = t.a[0] * t.x[0] + t.b[0] * t.y[0] + t.c[0];
  if (cx.cull ? area <= 0 : area == 0) return false;
  const int64_t sgn = area > 0 ? 1 : -1;
  for (int i = 0; i < 3; ++i) {
    t.a[i] *= sgn;
    t.b[i] *= sgn;
    t.c[i] *= sgn;
    t.thr[i] = (t.a[i] > 0 || (t.a[i] == 0 && t.b[i] > 0)) ? 0 : 1;
  }
  return true;
}

// Whether a small box (at most kProbe centres) holds a centre the triangle
// covers: the binning pass drops the many sliver and sub-pixel triangles
// of a dense mesh whose box holds centres they miss, so that the bands see
// only triangles that cover something.
constexpr int64_t kProbe = 4;
inline bool exact_covers_any(const Ctx& cx, const Exact& t) {
  if ((t.c1 - t.c0 + 1) * (t.r1 - t.r0 + 1) > kProbe) return true;
  const int64_t h = int64_t(1) << (cx.S - 1);
  for (int64_t r = t.r0; r <= t.r1; ++r) {
    const int64_t qy = (2 * r + 1 - cx.H) * h;
    for (int64_t c = t.c0; c <= t.c1; ++c) {
      const int64_t qx = (2 * c + 1 - cx.W) * h;
      if (t.a[0] * qx + t.c[0] + t.b[0] * qy >= t.thr[0] && t.a[1] * qx + t.c[1] + t.b[1] * qy >= t.thr[1] &&
          t.a[2] * qx + t.c[2] + t.b[2] * qy >= t.thr[2])
        return true;
    }
  }
  return false;
}

// exact_plane (after exact_edges): the float64 NDC depth plane of the
// unsnapped corners, anchored at corner 0; false where it is not finite.
inline bool exact_plane(const Ctx& cx, const int32_t* fv, Exact& t) {
  double nx[3], ny[3], nz[3], p[3][4];
  for (int i = 0; i < 3; ++i) cx.corner(fv[i], p[i]);
#if defined(__SSE2__)
  // The same quotients two at a time (a two-lane division costs a scalar
  // one's time: 6 divisions where 11 were the bound of this setup).
  for (int i = 0; i < 3; ++i) {
    double q[2];
    _mm_storeu_pd(q, _mm_div_pd(_mm_loadu_pd(p[i]), _mm_set1_pd(p[i][3])));
    nx[i] = q[0];
    ny[i] = q[1];
  }
  {
    double q[2];
    _mm_storeu_pd(q, _mm_div_pd(_mm_set_pd(p[1][2], p[0][2]), _mm_set_pd(p[1][3], p[0][3])));
    nz[0] = q[0];
    nz[1] = q[1];
    nz[2] = p[2][2] / p[2][3];
  }
#else
  for (int i = 0; i < 3; ++i) {
    nx[i] = p[i][0] / p[i][3];
    ny[i] = p[i][1] / p[i][3];
    nz[i] = p[i][2] / p[i][3];
  }
#endif
  const double dx1 = nx[1] - nx[0], dy1 = ny[1] - ny[0], dz1 = nz[1] - nz[0];
  const double dx2 = nx[2] - nx[0], dy2 = ny[2] - ny[0], dz2 = nz[2] - nz[0];
  const double d = dx1 * dy2 - dx2 * dy1;
#if defined(__SSE2__)
  {
    double q[2];
    _mm_storeu_pd(q, _mm_div_pd(_mm_set_pd(dx1 * dz2 - dx2 * dz1, dz1 * dy2 - dz2 * dy1), _mm_set1_pd(d)));
    t.zx = q[0];
    t.zy = q[1];
  }
#else
  t.zx = (dz1 * dy2 - dz2 * dy1) / d;
  t.zy = (dx1 * dz2 - dx2 * dz1) / d;
#endif
  if (!std::isfinite(t.zx) || !std::isfinite(t.zy)) return false;
  t.z0 = nz[0];
  t.x0 = nx[0];
  t.y0 = ny[0];
  return true;
}

// Float-path setup (raster.py _prepare_float); the bounding box is the
// projected one where every corner is in front of the near plane, else the
// whole screen (the torch path clips it tighter: both are conservative).
bool setup_float(const Ctx& cx, int64_t f, Float& t) {
  const int64_t* fv = cx.faces + 3 * f;
  double X[3], Y[3], Z[3], Wc[3];
  for (int i = 0; i < 3; ++i) {
    double p[4];
    cx.corner(fv[i], p);
    const double s = pow2_scale(max_abs4(p));
    X[i] = p[0] * s;
    Y[i] = p[1] * s;
    Z[i] = p[2] * s;
    Wc[i] = p[3] * s;
  }
  for (int i = 0; i < 3; ++i) {
    const int j = (i + 1) % 3, k = (i + 2) % 3;
    t.a[i] = Y[j] * Wc[k] - Wc[j] * Y[k];
    t.b[i] = Wc[j] * X[k] - X[j] * Wc[k];
    t.c[i] = X[j] * Y[k] - Y[j] * X[k];
  }
  const double det = X[0] * t.a[0] + Y[0] * t.b[0] + Wc[0] * t.c[0];
  if (cx.cull ? !(det > 0) : !(det != 0)) return false;
  const double inv_det = 1 / det;
  t.zc[0] = (t.a[0] * Z[0] + t.a[1] * Z[1] + t.a[2] * Z[2]) * inv_det;
  t.zc[1] = (t.b[0] * Z[0] + t.b[1] * Z[1] + t.b[2] * Z[2]) * inv_det;
  t.zc[2] = (t.c[0] * Z[0] + t.c[1] * Z[1] + t.c[2] * Z[2]) * inv_det;
  const double sgn = det > 0 ? 1.0 : -1.0;
  for (int i = 0; i < 3; ++i) {
    t.a[i] *= sgn;
    t.b[i] *= sgn;
    t.c[i] *= sgn;
    t.thr[i] = (t.a[i] > 0 || (t.a[i] == 0 && t.b[i] > 0)) ? 0.0 : std::numeric_limits<double>::denorm_min();
  }
  bool front = true;
  double xmin = INFINITY, xmax = -INFINITY, ymin = INFINITY, ymax = -INFINITY;
  for (int i = 0; i < 3; ++i) {
    if (!(Z[i] + Wc[i] >= 0 && Wc[i] > 0)) {
      front = false;
      break;
    }
    const double iw = 1 / Wc[i];
    xmin = std::min(xmin, X[i] * iw);
    xmax = std::max(xmax, X[i] * iw);
    ymin = std::min(ymin, Y[i] * iw);
    ymax = std::max(ymax, Y[i] * iw);
  }
  if (front) {
    const double m = 1e-3, hw = cx.W / 2.0, hh = cx.H / 2.0;
    auto cl = [](double v) { return std::min(1.0, std::max(-1.0, v)); };
    t.c0 = std::max<int64_t>(0, int64_t(std::ceil((cl(xmin) + 1) * hw - 0.5 - m)));
    t.c1 = std::min<int64_t>(cx.W - 1, int64_t(std::floor((cl(xmax) + 1) * hw - 0.5 + m)));
    t.r0 = std::max<int64_t>(0, int64_t(std::ceil((1 - cl(ymax)) * hh - 0.5 - m)));
    t.r1 = std::min<int64_t>(cx.H - 1, int64_t(std::floor((1 - cl(ymin)) * hh - 0.5 + m)));
  } else {
    t.c0 = 0;
    t.c1 = cx.W - 1;
    t.r0 = 0;
    t.r1 = cx.H - 1;
  }
  return t.c0 <= t.c1 && t.r0 <= t.r1;
}

// The vertex pass's record of vertex v: outcode (from the power-of-two
// scaled clip coordinates) and, where w > 0 and the projection is inside
// the guard band, the snapped position; a non-finite coordinate sets bad.
inline uint8_t vertex_one(const Ctx& vc, int64_t v, double vsx, double vsy, bool snap, Vert* out,
                       std::atomic<bool>& bad) {
  double p[4];
  vc.corner(v, p);
  if (!(std::isfinite(p[0]) && std::isfinite(p[1]) && std::isfinite(p[2]) && std::isfinite(p[3])))
    bad.store(true, std::memory_order_relaxed);
  const double s = pow2_scale(max_abs4(p));
  const double X = p[0] * s, Y = p[1] * s, Z = p[2] * s, Wc = p[3] * s;
  uint8_t code = uint8_t((X > Wc) | ((X < -Wc) << 1) | ((Y > Wc) << 2) | ((Y < -Wc) << 3) | ((Z > Wc) << 4) |
                         ((Z < -Wc) << 5));
  Vert& o = out[v];
  o.x = o.y = 0;
  if (snap && p[3] > 0) {
    const double fx = (p[0] / p[3]) * vsx, fy = (p[1] / p[3]) * vsy;
    if (std::abs(fx) <= kGuard && std::abs(fy) <= kGuard) {
      code |= kSnapped;
      o.x = int32_t(round_even(fx));
      o.y = int32_t(round_even(fy));
    }
  }
  o.code = code;
  return code;
}

#if DT_HAVE_AVX2
// vertex_one for four vertices at a time (AVX2, the same float64
// operations lane by lane, so the same records): vertices lo .. the last
// whole group before hi; a group with a non-finite coordinate or a scale
// outside pow2_scale's exponent-bit range takes vertex_one. Returns where
// it stopped.
__attribute__((target("avx2,fma"))) int64_t vertices_avx2(const Ctx& vc, int64_t lo, int64_t hi, double vsx,
                                                          double vsy, bool snap, Vert* out, std::atomic<bool>& bad,
                                                          bool& inside) {
  const __m256d sign = _mm256_set1_pd(-0.0), inf = _mm256_set1_pd(INFINITY), guard = _mm256_set1_pd(kGuard);
  const __m256d magic = _mm256_set1_pd(6755399441055744.0), zero = _mm256_setzero_pd();
  const __m256d sxv = _mm256_set1_pd(vsx), syv = _mm256_set1_pd(vsy);
  const __m256i exp_mask = _mm256_set1_epi64x(0x7ff), top = _mm256_set1_epi64x(2045);
  int64_t v = lo;
  for (; v + 4 <= hi; v += 4) {
    __m256d r[4];  // vertex v + i's (x, y, z, w)
    if (vc.f32) {
      const float* q = static_cast<const float*>(vc.pos) + 4 * v;
      for (int i = 0; i < 4; ++i) r[i] = _mm256_cvtps_pd(_mm_loadu_ps(q + 4 * i));
    } else {
      const double* q = static_cast<const double*>(vc.pos) + 4 * v;
      for (int i = 0; i < 4; ++i) r[i] = _mm256_loadu_pd(q + 4 * i);
    }
    // Transpose: x, y, z, w of the four vertices.
    const __m256d t0 = _mm256_unpacklo_pd(r[0], r[1]), t1 = _mm256_unpackhi_pd(r[0], r[1]);
    const __m256d t2 = _mm256_unpacklo_pd(r[2], r[3]), t3 = _mm256_unpackhi_pd(r[2], r[3]);
    const __m256d x = _mm256_permute2f128_pd(t0, t2, 0x20), y = _mm256_permute2f128_pd(t1, t3, 0x20);
    const __m256d z = _mm256_permute2f128_pd(t0, t2, 0x31), w = _mm256_permute2f128_pd(t1, t3, 0x31);
    const __m256d ax = _mm256_andnot_pd(sign, x), ay = _mm256_andnot_pd(sign, y);
    const __m256d az = _mm256_andnot_pd(sign, z), aw = _mm256_andnot_pd(sign, w);
    const __m256d fin = _mm256_and_pd(_mm256_and_pd(_mm256_cmp_pd(ax, inf, _CMP_LT_OQ), _mm256_cmp_pd(ay, inf, _CMP_LT_OQ)),
                                      _mm256_and_pd(_mm256_cmp_pd(az, inf, _CMP_LT_OQ), _mm256_cmp_pd(aw, inf, _CMP_LT_OQ)));
    // All finite: the max of the |coordinates| is std::max's.
    const __m256d m = _mm256_max_pd(_mm256_max_pd(ax, ay), _mm256_max_pd(az, aw));
    const __m256i be = _mm256_and_si256(_mm256_srli_epi64(_mm256_castpd_si256(m), 52), exp_mask);
    const __m256i normal = _mm256_andnot_si256(_mm256_cmpeq_epi64(be, _mm256_setzero_si256()), _mm256_cmpgt_epi64(top, be));
    if (_mm256_movemask_pd(_mm256_and_pd(fin, _mm256_castsi256_pd(normal))) != 0xf) {
      for (int i = 0; i < 4; ++i) inside &= vertex_one(vc, v + i, vsx, vsy, snap, out, bad) == kSnapped;
      continue;
    }
    const __m256d s = _mm256_castsi256_pd(_mm256_slli_epi64(_mm256_sub_epi64(top, be), 52));
    const __m256d X = _mm256_mul_pd(x, s), Y = _mm256_mul_pd(y, s), Z = _mm256_mul_pd(z, s), Wc = _mm256_mul_pd(w, s);
    const __m256d nW = _mm256_xor_pd(Wc, sign);
    __m256i code = _mm256_setzero_si256();
    const __m256d tests[6] = {_mm256_cmp_pd(X, Wc, _CMP_GT_OQ), _mm256_cmp_pd(X, nW, _CMP_LT_OQ),
                              _mm256_cmp_pd(Y, Wc, _CMP_GT_OQ), _mm256_cmp_pd(Y, nW, _CMP_LT_OQ),
                              _mm256_cmp_pd(Z, Wc, _CMP_GT_OQ), _mm256_cmp_pd(Z, nW, _CMP_LT_OQ)};
    for (int b = 0; b < 6; ++b)
      code = _mm256_or_si256(code, _mm256_and_si256(_mm256_castpd_si256(tests[b]), _mm256_set1_epi64x(1 << b)));
    __m128i qx = _mm_setzero_si128(), qy = _mm_setzero_si128();
    if (snap) {
      const __m256d fx = _mm256_mul_pd(_mm256_div_pd(x, w), sxv), fy = _mm256_mul_pd(_mm256_div_pd(y, w), syv);
      const __m256d ok = _mm256_and_pd(_mm256_cmp_pd(w, zero, _CMP_GT_OQ),
                                       _mm256_and_pd(_mm256_cmp_pd(_mm256_andnot_pd(sign, fx), guard, _CMP_LE_OQ),
                                                     _mm256_cmp_pd(_mm256_andnot_pd(sign, fy), guard, _CMP_LE_OQ)));
      code = _mm256_or_si256(code, _mm256_and_si256(_mm256_castpd_si256(ok), _mm256_set1_epi64x(kSnapped)));
      // round_even, then the (integral) values as int32; zero where not snapped.
      const __m256d rx = _mm256_and_pd(ok, _mm256_sub_pd(_mm256_add_pd(fx, magic), magic));
      const __m256d ry = _mm256_and_pd(ok, _mm256_sub_pd(_mm256_add_pd(fy, magic), magic));
      qx = _mm256_cvttpd_epi32(rx);
      qy = _mm256_cvttpd_epi32(ry);
    }
    alignas(32) int32_t ox[4], oy[4];
    alignas(32) int64_t oc[4];
    _mm_store_si128(reinterpret_cast<__m128i*>(ox), qx);
    _mm_store_si128(reinterpret_cast<__m128i*>(oy), qy);
    _mm256_store_si256(reinterpret_cast<__m256i*>(oc), code);
    inside &= _mm256_movemask_pd(_mm256_castsi256_pd(_mm256_cmpeq_epi64(code, _mm256_set1_epi64x(kSnapped)))) == 0xf;
    for (int i = 0; i < 4; ++i) {
      Vert& o = out[v + i];
      o.x = ox[i];
      o.y = oy[i];
      o.code = uint8_t(oc[i]);
    }
  }
  return v;
}

#endif

#if DT_HAVE_AVX2
// The triangle pass's eight-triangle filter (AVX2): of triangles fv[0..8)
// (24 vertex ids), a mask of those the scalar tests would drop that it
// proves dropped: every corner outside one clip plane (the outcodes), or
// all snapped and an empty box of centres, or all snapped, a box of at most
// kProbe centres and an extent below 2^20 units, and degenerate / culled or
// covering none of the box's centres. Those tests are integer decisions,
// made here on exact values (int32 boxes; the edge functions in float64,
// exact: below 2^20 * 2^29 * 4 < 2^53), so the lanes the scalar pass sees
// (the rest: about a quarter of a dense mesh's) give it the same outcome,
// and the result does not depend on which path ran. Any vertex id out of
// range: none dropped (the scalar pass reports it).
// (GCC: lambdas do not inherit the target attribute, hence these helpers.)
DT_AVX2 unsigned bits(__m256i m) { return unsigned(_mm256_movemask_ps(_mm256_castsi256_ps(m))); }
DT_AVX2 __m128i half_of(__m256i v, int half) {
  return half ? _mm256_extracti128_si256(v, 1) : _mm256_castsi256_si128(v);
}
// Lanes 4 half .. 4 half + 3 of eight int32 as float64 (exact), and of an
// int32 lane mask as a float64 lane mask.
DT_AVX2 __m256d half8(__m256i v, int half) { return _mm256_cvtepi32_pd(half_of(v, half)); }
DT_AVX2 __m256d mask_half8(__m256i m, int half) { return _mm256_castsi256_pd(_mm256_cvtepi32_epi64(half_of(m, half))); }

// What the filter learnt of the lanes it kept: `direct` marks those with a
// small box whose triangle it found covering a centre (the exact tests'
// outcome: the scalar pass would list them), with their Live fields, so
// that those are listed without the scalar tests.
struct Group8 {
  int32_t v[3][8], x[3][8], y[3][8], c0[8], r0[8], r1[8], nc[8];
  unsigned direct, cov[kProbe];  // cov[s]: the lanes whose triangle covers centre slot s
};

template <bool kAllIn>
__attribute__((target("avx2,fma"))) unsigned dropped8(const int64_t* fv, const Vert* vert, int64_t nv, int64_t W,
                                                      int64_t H, int S, bool cull, Group8& g) {
  g.direct = 0;
  for (int s = 0; s < int(kProbe); ++s) g.cov[s] = 0;
  const __m256i zero = _mm256_setzero_si256(), lim = _mm256_set1_epi64x(nv - 1);
  __m256i badv = zero;
  for (int i = 0; i < 6; ++i) {
    const __m256i v = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(fv + 4 * i));
    badv = _mm256_or_si256(badv, _mm256_or_si256(_mm256_cmpgt_epi64(zero, v), _mm256_cmpgt_epi64(v, lim)));
  }
  if (!_mm256_testz_si256(badv, badv)) return 0;
  // The low halves of the int64 ids (< 2^31 here), corner k of lane l at
  // int32 6 l + 2 k; a Vert is three int32 (x, y, code and padding).
  const int* fi = reinterpret_cast<const int*>(fv);
  const int* vb = reinterpret_cast<const int*>(vert);
  const __m256i lane6 = _mm256_setr_epi32(0, 6, 12, 18, 24, 30, 36, 42), three = _mm256_set1_epi32(3);
  // kAllIn: every vertex snapped and inside the view volume (the vertex
  // pass says so): every code is kSnapped, not read.
  __m256i x[3], y[3], code = _mm256_set1_epi32(kAllIn ? kSnapped : 0xff);
  for (int k = 0; k < 3; ++k) {
    const __m256i id = _mm256_i32gather_epi32(fi, _mm256_add_epi32(lane6, _mm256_set1_epi32(2 * k)), 4);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(g.v[k]), id);
    const __m256i o = _mm256_mullo_epi32(id, three);
    x[k] = _mm256_i32gather_epi32(vb, o, 4);
    y[k] = _mm256_i32gather_epi32(vb + 1, o, 4);
    if (!kAllIn) code = _mm256_and_si256(code, _mm256_i32gather_epi32(vb + 2, o, 4));
  }
  const unsigned out = bits(_mm256_cmpgt_epi32(_mm256_and_si256(code, _mm256_set1_epi32(0x7f)), zero));
  const __m256i snap = _mm256_cmpeq_epi32(_mm256_and_si256(code, _mm256_set1_epi32(kSnapped)),
                                          _mm256_set1_epi32(kSnapped));
  // exact_box in int32: |corner| <= 2^29 and |(n - 1) h| < 2^27.
  const int32_t h = int32_t(1) << (S - 1);
  const __m256i Kx = _mm256_set1_epi32(int32_t((W - 1) * h)), Ky = _mm256_set1_epi32(int32_t((H - 1) * h));
  const __m128i sh = _mm_cvtsi32_si128(S);
  const __m256i xmin = _mm256_min_epi32(_mm256_min_epi32(x[0], x[1]), x[2]);
  const __m256i xmax = _mm256_max_epi32(_mm256_max_epi32(x[0], x[1]), x[2]);
  const __m256i ymin = _mm256_min_epi32(_mm256_min_epi32(y[0], y[1]), y[2]);
  const __m256i ymax = _mm256_max_epi32(_mm256_max_epi32(y[0], y[1]), y[2]);
  const __m256i c0 = _mm256_max_epi32(zero, _mm256_sub_epi32(zero, _mm256_sra_epi32(
                                                                  _mm256_sub_epi32(zero, _mm256_add_epi32(xmin, Kx)), sh)));
  const __m256i c1 = _mm256_min_epi32(_mm256_set1_epi32(int32_t(W - 1)), _mm256_sra_epi32(_mm256_add_epi32(xmax, Kx), sh));
  const __m256i r0 = _mm256_max_epi32(zero, _mm256_sub_epi32(zero, _mm256_sra_epi32(
                                                                  _mm256_sub_epi32(zero, _mm256_add_epi32(ymin, Ky)), sh)));
  const __m256i r1 = _mm256_min_epi32(_mm256_set1_epi32(int32_t(H - 1)), _mm256_sra_epi32(_mm256_add_epi32(ymax, Ky), sh));
  const __m256i empty = _mm256_or_si256(_mm256_cmpgt_epi32(c0, c1), _mm256_cmpgt_epi32(r0, r1));
  const unsigned snapped = bits(snap), dropped_box = snapped & bits(empty);
  const __m256i one = _mm256_set1_epi32(1), five = _mm256_set1_epi32(int32_t(kProbe) + 1);
  const __m256i nc = _mm256_add_epi32(_mm256_sub_epi32(c1, c0), one), nr = _mm256_add_epi32(_mm256_sub_epi32(r1, r0), one);
  const __m256i cnt = _mm256_mullo_epi32(nc, nr), ext = _mm256_set1_epi32(1 << 20);
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(g.nc), nc);
  __m256i small = _mm256_and_si256(_mm256_cmpgt_epi32(five, nc), _mm256_cmpgt_epi32(five, nr));
  small = _mm256_and_si256(small, _mm256_cmpgt_epi32(five, cnt));
  small = _mm256_and_si256(small, _mm256_cmpgt_epi32(ext, _mm256_sub_epi32(xmax, xmin)));
  small = _mm256_and_si256(small, _mm256_cmpgt_epi32(ext, _mm256_sub_epi32(ymax, ymin)));
  const unsigned small_bits = bits(small) & snapped & ~bits(empty) & 0xffu;
  if (!small_bits) return (out | dropped_box) & 0xffu;
  // The box's centres, at most kProbe = 4 slots: one column (0, s), two
  // columns (s & 1, s >> 1), else one row (s, 0); slot s in use if s < cnt.
  for (int k = 0; k < 3; ++k) {
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(g.x[k]), x[k]);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(g.y[k]), y[k]);
  }
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(g.r0), r0);
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(g.r1), r1);
  _mm256_storeu_si256(reinterpret_cast<__m256i*>(g.c0), c0);
  // Slots past the largest box of a small lane are skipped (most boxes of
  // a dense mesh hold one centre).
  int slots = 1;
  for (; slots < int(kProbe); ++slots)
    if (!(bits(_mm256_cmpgt_epi32(cnt, _mm256_set1_epi32(slots))) & small_bits)) break;
  const __m256i two_h = _mm256_set1_epi32(2 * h);
  const __m256i nc1 = _mm256_cmpeq_epi32(nc, one), nc2 = _mm256_cmpeq_epi32(nc, _mm256_set1_epi32(2));
  __m256i qx[kProbe], qy[kProbe], use[kProbe];
  for (int s = 0; s < slots; ++s) {
    const __m256i sv = _mm256_set1_epi32(s);
    __m256i co = _mm256_blendv_epi8(sv, _mm256_set1_epi32(s & 1), nc2);
    co = _mm256_blendv_epi8(co, zero, nc1);
    __m256i ro = _mm256_blendv_epi8(zero, _mm256_set1_epi32(s >> 1), nc2);
    ro = _mm256_blendv_epi8(ro, sv, nc1);
    qx[s] = _mm256_sub_epi32(_mm256_mullo_epi32(_mm256_add_epi32(c0, co), two_h), Kx);
    qy[s] = _mm256_sub_epi32(_mm256_mullo_epi32(_mm256_add_epi32(r0, ro), two_h), Ky);
    use[s] = _mm256_cmpgt_epi32(cnt, sv);
  }
  unsigned keep_small = 0;  // small lanes whose triangle is kept (not degenerate, not culled) and covers a centre
  for (int half = 0; half < 2; ++half) {
    __m256d X[3], Y[3], a[3], b[3], c[3];
    for (int i = 0; i < 3; ++i) X[i] = half8(x[i], half), Y[i] = half8(y[i], half);
    for (int i = 0; i < 3; ++i) {
      const int j = (i + 1) % 3, k = (i + 2) % 3;
      a[i] = half8(_mm256_sub_epi32(y[k], y[j]), half);
      b[i] = half8(_mm256_sub_epi32(x[j], x[k]), half);
      c[i] = _mm256_sub_pd(_mm256_setzero_pd(), _mm256_add_pd(_mm256_mul_pd(a[i], X[j]), _mm256_mul_pd(b[i], Y[j])));
    }
    const __m256d zd = _mm256_setzero_pd();
    const __m256d area = _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(a[0], X[0]), _mm256_mul_pd(b[0], Y[0])), c[0]);
    const __m256d ok = cull ? _mm256_cmp_pd(area, zd, _CMP_GT_OQ) : _mm256_cmp_pd(area, zd, _CMP_NEQ_OQ);
    const __m256d sgn = _mm256_blendv_pd(_mm256_set1_pd(1.0), _mm256_set1_pd(-1.0), _mm256_cmp_pd(area, zd, _CMP_LT_OQ));
    __m256d thr[3];
    for (int i = 0; i < 3; ++i) {
      a[i] = _mm256_mul_pd(a[i], sgn);
      b[i] = _mm256_mul_pd(b[i], sgn);
      c[i] = _mm256_mul_pd(c[i], sgn);
      const __m256d own = _mm256_or_pd(_mm256_cmp_pd(a[i], zd, _CMP_GT_OQ),
                                       _mm256_and_pd(_mm256_cmp_pd(a[i], zd, _CMP_EQ_OQ), _mm256_cmp_pd(b[i], zd, _CMP_GT_OQ)));
      thr[i] = _mm256_blendv_pd(_mm256_set1_pd(1.0), zd, own);
    }
    __m256d cov = zd;
    for (int s = 0; s < slots; ++s) {
      const __m256d px = half8(qx[s], half), py = half8(qy[s], half);
      __m256d in = mask_half8(use[s], half);
      for (int i = 0; i < 3; ++i) {
        const __m256d e = _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(a[i], px), c[i]), _mm256_mul_pd(b[i], py));
        in = _mm256_and_pd(in, _mm256_cmp_pd(e, thr[i], _CMP_GE_OQ));
      }
      cov = _mm256_or_pd(cov, in);
      g.cov[s] |= unsigned(_mm256_movemask_pd(in)) << (4 * half);
    }
    keep_small |= unsigned(_mm256_movemask_pd(_mm256_and_pd(ok, cov))) << (4 * half);
  }
  g.direct = small_bits & keep_small;
  return (out | dropped_box | (small_bits & ~keep_small)) & 0xffu;
}

// The z-buffer's exact-path row loop (plain mode) four centres at a time:
// columns cs .. ce of one row of one triangle, E0..E2 its edge functions at
// cs and s0..s2 their steps a column, zb / ib the band's depths and ids of
// the row (indexed by column; three slots of slack past the last). The same
// int64 edge tests, the same float64 depth (z0 + zx (x - x0)) + dy and the
// same (depth, id) order as the scalar loop, lane by lane: each centre is
// its own decision, so the result is the scalar one. Lanes past ce write
// back what they read.
// E + i s in lane i.
DT_AVX2 __m256i lanes_from(int64_t E, int64_t s) {
  return _mm256_add_epi64(_mm256_set1_epi64x(E), _mm256_setr_epi64x(0, s, s + s, s + s + s));
}

__attribute__((target("avx2,fma"))) void exact_row_avx2(double* zb, int64_t* ib, const double* xs, int64_t cs,
                                                        int64_t ce, int64_t E0, int64_t E1, int64_t E2, int64_t s0,
                                                        int64_t s1, int64_t s2, int64_t t0, int64_t t1, int64_t t2,
                                                        double z0, double zx, double x0, double dy, int64_t f) {
  const __m256i lane = _mm256_setr_epi64x(0, 1, 2, 3);
  __m256i e0 = lanes_from(E0, s0), e1 = lanes_from(E1, s1), e2 = lanes_from(E2, s2);
  const __m256i d0 = _mm256_set1_epi64x(4 * s0), d1 = _mm256_set1_epi64x(4 * s1), d2 = _mm256_set1_epi64x(4 * s2);
  // E >= t as E > t - 1 (t is 0 or 1).
  const __m256i u0 = _mm256_set1_epi64x(t0 - 1), u1 = _mm256_set1_epi64x(t1 - 1), u2 = _mm256_set1_epi64x(t2 - 1);
  const __m256d vz0 = _mm256_set1_pd(z0), vzx = _mm256_set1_pd(zx), vx0 = _mm256_set1_pd(x0), vdy = _mm256_set1_pd(dy);
  const __m256d lo = _mm256_set1_pd(-1.0), hi = _mm256_set1_pd(1.0);
  const __m256i vf = _mm256_set1_epi64x(f);
  for (int64_t c = cs; c <= ce; c += 4) {
    __m256i in = _mm256_cmpgt_epi64(_mm256_set1_epi64x(ce - c + 1), lane);
    in = _mm256_and_si256(in, _mm256_cmpgt_epi64(e0, u0));
    in = _mm256_and_si256(in, _mm256_cmpgt_epi64(e1, u1));
    in = _mm256_and_si256(in, _mm256_cmpgt_epi64(e2, u2));
    e0 = _mm256_add_epi64(e0, d0), e1 = _mm256_add_epi64(e1, d1), e2 = _mm256_add_epi64(e2, d2);
    if (_mm256_testz_si256(in, in)) continue;
    const __m256d z = _mm256_add_pd(_mm256_add_pd(vz0, _mm256_mul_pd(vzx, _mm256_sub_pd(_mm256_loadu_pd(xs + c), vx0))), vdy);
    const __m256d old = _mm256_loadu_pd(zb + c);
    const __m256i oid = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(ib + c));
    const __m256d range = _mm256_and_pd(_mm256_cmp_pd(z, lo, _CMP_GE_OQ), _mm256_cmp_pd(z, hi, _CMP_LE_OQ));
    const __m256d nearer = _mm256_or_pd(_mm256_cmp_pd(z, old, _CMP_LT_OQ),
                                        _mm256_and_pd(_mm256_cmp_pd(z, old, _CMP_EQ_OQ),
                                                      _mm256_castsi256_pd(_mm256_cmpgt_epi64(oid, vf))));
    const __m256d win = _mm256_and_pd(_mm256_castsi256_pd(in), _mm256_and_pd(range, nearer));
    _mm256_storeu_pd(zb + c, _mm256_blendv_pd(old, z, win));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(ib + c),
                        _mm256_castpd_si256(_mm256_blendv_pd(_mm256_castsi256_pd(oid), _mm256_castsi256_pd(vf), win)));
  }
}
#endif

// The fused pass (raster_fused): called by the thread that resolved band
// R0 .. R1 - 1 of batch item bi, right after its rows of ids (all_ids:
// the layer's whole [B * H * W] ids) are written, while they and the
// band's triangles are in cache; once per layer.
struct BandSink {
  virtual void band(const int64_t* all_ids, int64_t bi, int64_t R0, int64_t R1, int64_t layer) = 0;

 protected:
  ~BandSink() = default;
};

// The ids: with split, one [B * H * W] tensor a layer, else one
// [K * B * H * W] tensor, layer-major. Empty tensors on bad input.
std::tuple<std::vector<Tensor>, Tensor> raster_impl(Tensor pos, Tensor faces, int64_t H, int64_t W, bool cull,
                                                    int64_t bits, Tensor floor_z, Tensor floor_id, bool count,
                                                    int64_t layers, BandSink* sink, bool keep_depth, bool split);

}  // namespace

std::tuple<Tensor, Tensor> raster(Tensor pos, Tensor faces, int64_t H, int64_t W,
                                                bool cull, int64_t bits, Tensor floor_z,
                                                Tensor floor_id, bool count, int64_t layers) {
  auto [ids, depth] = raster_impl(pos, faces, H, W, cull, bits, floor_z, floor_id, count, layers, nullptr, true, false);
  return {ids[0], depth};
}

namespace {

std::tuple<std::vector<Tensor>, Tensor> raster_impl(Tensor pos, Tensor faces, int64_t H, int64_t W, bool cull,
                                                    int64_t bits, Tensor floor_z, Tensor floor_id, bool count,
                                                    int64_t layers, BandSink* sink, bool keep_depth, bool split) {
  DT_CHECK(pos.is_cpu() && (pos.scalar_type() == kFloat64 || pos.scalar_type() == kFloat32) &&
                  pos.dim() == 3 && pos.size(2) == 4,
              "raster: pos must be a CPU float32 or float64 tensor [B, V, 4]");
  DT_CHECK(faces.is_cpu() && faces.scalar_type() == kInt64 && faces.dim() == 2 &&
                  faces.size(1) == 3,
              "raster: faces must be a CPU int64 tensor [F, 3]");
  DT_CHECK(H > 0 && W > 0 && bits >= 0 && bits <= 16, "raster: bad resolution or sub-pixel bits");
  pos = contig(pos);
  faces = contig(faces);
  const int64_t B = pos.size(0), V = pos.size(1), F = faces.size(0), HW = H * W;
  DT_CHECK(F < kFloatBit && V <= std::numeric_limits<int32_t>::max(),
              "raster: at most 2^30 - 1 triangles and 2^31 - 1 vertices");
  const bool has_floor = floor_z.numel() > 0;
  DT_CHECK(layers >= 1 && (layers == 1 || (!has_floor && !count)),
              "raster: layers >= 1, and 1 with a floor or a count");
  const int64_t K = layers;
  if (has_floor) {
    DT_CHECK(floor_z.numel() == B * HW && floor_id.numel() == B * HW &&
                    floor_z.scalar_type() == kFloat64 && floor_id.scalar_type() == kInt64,
                "raster: floor must be float64 depth and int64 ids, [B * H * W] each");
    floor_z = contig(floor_z);
    floor_id = contig(floor_id);
  }
  // K > 1: the ids of each layer contiguous and the depth of the K-th
  // layer only (the floor of any further layer). Split, each layer is an
  // allocation of its own: four layers at 1024^2 in one were 32 MiB,
  // glibc's largest mmap threshold, so every call mapped fresh memory and
  // took ~8,200 page faults to fill it (16 of 69 ms, one thread).
  std::vector<Tensor> ids;
  std::vector<int64_t*> lay(K);  // layer k's [B * H * W] ids
  for (int64_t k = 0; k < K; ++k) {
    if (split || k == 0) ids.push_back(empty({(split ? 1 : K) * B * HW}, kInt64));
    lay[k] = split ? ids[k].mutable_data_ptr<int64_t>() : ids[0].mutable_data_ptr<int64_t>() + k * B * HW;
  }
  DT_CHECK(!sink || (!has_floor && !count), "raster: the fused pass takes no floor and no count");
  DT_CHECK(keep_depth || sink, "raster: the depth is kept unless fused");
  auto depth = empty({keep_depth ? B * HW : 0}, kFloat64);
  const double* fz = has_floor ? floor_z.mutable_data_ptr<double>() : nullptr;
  const int64_t* fi = has_floor ? floor_id.mutable_data_ptr<int64_t>() : nullptr;
  double* out_z = keep_depth ? depth.mutable_data_ptr<double>() : nullptr;
  const int64_t S = bits;
  const double sx = S > 0 ? double(W << (S - 1)) : 0.0, sy = S > 0 ? -double(H << (S - 1)) : 0.0;
  std::vector<double> xs(W + 4, 0.0), ys(H);  // + 4: the four-pixel loop's masked lanes past the last column
  for (int64_t c = 0; c < W; ++c) xs[c] = (double(c) + 0.5) * (2.0 / double(W)) - 1.0;
  for (int64_t r = 0; r < H; ++r) ys[r] = -((double(r) + 0.5) * (2.0 / double(H)) - 1.0);
  const int64_t nb = (H + kBand - 1) / kBand;
  // Not value-initialised (a 12-byte record a vertex, every one written by
  // the vertex pass; zeroing a big mesh's first cost a tenth of that pass).
  std::unique_ptr<Vert[]> vert(new Vert[V]);
  // Non-finite positions or out-of-range indices, found in passes that read
  // every one of them anyway (rasterize leaves its own checks of a big mesh
  // to these): the kernel then returns empty tensors, and the caller names
  // the problem.
  std::atomic<bool> bad{false};
  // Whether every vertex of this batch item is snapped and inside the view
  // volume (a mesh in full view): the eight-triangle filter then skips the
  // outcodes.
  std::atomic<bool> all_in{true};

  for (int64_t bi = 0; bi < B; ++bi) {
    all_in.store(true, std::memory_order_relaxed);
    const bool f32 = pos.scalar_type() == kFloat32;
    const char* P = static_cast<const char*>(pos.data_ptr()) + bi * V * 4 * (f32 ? 4 : 8);
    // Vertices: the float path's scale and outcode, the exact path's snap.
    const Ctx cx{P, f32, faces.mutable_data_ptr<int64_t>(), vert.get(), H, W, S, cull};
    constexpr int64_t kVertBlock = 16384;  // vertices an item of the vertex pass
    dynamic_for((V + kVertBlock - 1) / kVertBlock, [&](auto&& next_block) {
      // Locals: the outcode is a byte store, which may alias anything.
      const Ctx vc = cx;
      const double vsx = sx, vsy = sy;
      const bool snap = S > 0;
      Vert* const out = vert.get();
      for (int64_t blk; (blk = next_block()) >= 0;) {
        const int64_t lo = blk * kVertBlock, hi = std::min(V, lo + kVertBlock);
        int64_t v = lo;
        bool inside = true;
#if DT_HAVE_AVX2
        if (simd_on()) v = vertices_avx2(vc, lo, hi, vsx, vsy, snap, out, bad, inside);
#endif
        for (; v < hi; ++v) inside &= vertex_one(vc, v, vsx, vsy, snap, out, bad) == kSnapped;
        if (!inside) all_in.store(false, std::memory_order_relaxed);
      }
    });
    // Triangles, in chunks: which path, and the bands of rows they touch,
    // listed per chunk for the few that survive (the binning then never
    // scans the dead ones), with a count per band.
    const int64_t chunk = std::max<int64_t>(4096, (F + 63) / 64);
    const int64_t nch = std::max<int64_t>(1, (F + chunk - 1) / chunk);
    // The eight-triangle filter: snapping on (S > 0), its int32 box
    // arithmetic exact (pixel centres within 2^27 units, as
    // geometry/raster.py _subpixel_bits chooses S), int32 gather offsets
    // (3 V < 2^31), and the switch the tests turn (kernels.h set_simd).
    const bool simd = simd_on() && S > 0 && (std::max(H, W) << S) <= (int64_t(1) << 28) &&
                      V < (int64_t(1) << 31) / 3,
               inside_all = all_in.load();
    (void)simd, (void)inside_all;  // read only where the build has the AVX2 paths
    std::vector<int64_t> cnt(nch * nb, 0);
    std::vector<std::vector<Live>> live(nch);
    // Chunks handed out one at a time (as the bands are): on a machine
    // shared with other work a static split waits for the slower thread.
    dynamic_for(nch, [&](auto&& next_chunk) {
      const Ctx tc = cx;  // a local copy: the list writes could alias the captured one (reloaded per triangle)
      const uint64_t nv = uint64_t(V);
      Exact e;
      Float fl;
      for (int64_t ch; (ch = next_chunk()) >= 0;) {
        const int64_t lo = ch * chunk, hi = std::min(F, lo + chunk);
        std::vector<Live>& out = live[ch];
        out.clear();
        // Room for a dense mesh's survivors (about a quarter): growing the
        // list by doubling copied it, a few percent of rasterize.
        out.reserve((hi - lo) / 3 + 64);
        auto one = [&](int64_t f) {
          const int64_t* fv = tc.faces + 3 * f;
          if ((uint64_t(fv[0]) >= nv) | (uint64_t(fv[1]) >= nv) | (uint64_t(fv[2]) >= nv)) {
            bad.store(true, std::memory_order_relaxed);
            return;
          }
          const uint8_t c0 = tc.vert[fv[0]].code, c1 = tc.vert[fv[1]].code, c2 = tc.vert[fv[2]].code;
          if (c0 & c1 & c2 & ~kSnapped) return;
          if (c0 & c1 & c2 & kSnapped) {
            if (!exact_box(tc, f, e) || !exact_edges(tc, e) || !exact_covers_any(tc, e)) return;
            out.push_back({int32_t(f), int32_t(e.r0 / kBand), int32_t(e.r1 / kBand),
                           {int32_t(fv[0]), int32_t(fv[1]), int32_t(fv[2])},
                           {int32_t(e.x[0]), int32_t(e.x[1]), int32_t(e.x[2])},
                           {int32_t(e.y[0]), int32_t(e.y[1]), int32_t(e.y[2])}});
          } else {
            if (!setup_float(tc, f, fl)) return;
            out.push_back({int32_t(f) | kFloatBit, int32_t(fl.r0 / kBand), int32_t(fl.r1 / kBand), {}, {}, {}});
          }
        };
        int64_t f = lo;
#if DT_HAVE_AVX2
        if (simd) {
          // Eight at a time through the filter; the scalar tests see only
          // the lanes it could neither drop nor list (no prefetches here:
          // measured, they did not pay for themselves).
          Group8 g;
          for (; f + 8 <= hi; f += 8) {
            unsigned keep = ~(inside_all ? dropped8<true>(tc.faces + 3 * f, tc.vert, V, tc.W, tc.H, int(tc.S), tc.cull, g)
                                         : dropped8<false>(tc.faces + 3 * f, tc.vert, V, tc.W, tc.H, int(tc.S), tc.cull, g)) &
                            0xffu;
            for (; keep; keep &= keep - 1) {
              const int l = __builtin_ctz(keep);
              if (!(g.direct >> l & 1)) {
                one(f + l);
                continue;
              }
              int32_t mask = 0;
              for (int sl = 0; sl < int(kProbe); ++sl) mask |= int32_t(g.cov[sl] >> l & 1) << sl;
              out.push_back({int32_t(f + l), g.r0[l] / int32_t(kBand), g.r1[l] / int32_t(kBand),
                             {g.v[0][l], g.v[1][l], g.v[2][l]},
                             {g.c0[l], g.nc[l], kDirect},
                             {g.r0[l], mask, 0}});
            }
          }
        }
#endif
        for (; f < hi; ++f) {
          if (f + kAhead < hi) {
            const int64_t* fa = tc.faces + 3 * (f + kAhead);
            for (int i = 0; i < 3; ++i)
              if (uint64_t(fa[i]) < nv) DT_PREFETCH(tc.vert + fa[i], false);
          }
          one(f);
        }
        for (const Live& t : out)
          for (int32_t b = t.band0; b <= t.band1; ++b) ++cnt[ch * nb + b];
      }
    });
    if (bad.load()) return {{empty({0}, kInt64)}, empty({0}, kFloat64)};
    std::vector<int64_t> start(nb + 1, 0);
    int64_t total = 0;
    for (int64_t b = 0; b < nb; ++b) {
      start[b] = total;
      for (int64_t ch = 0; ch < nch; ++ch) {
        const int64_t n = cnt[ch * nb + b];
        cnt[ch * nb + b] = total;
        total += n;
      }
    }
    start[nb] = total;
    std::unique_ptr<const Live*[]> list(new const Live*[total]);  // every entry written below: not zeroed first
    dynamic_for(nch, [&](auto&& next_chunk) {
      for (int64_t ch; (ch = next_chunk()) >= 0;)
        for (const Live& t : live[ch])
          for (int32_t b = t.band0; b <= t.band1; ++b) list[cnt[ch * nb + b]++] = &t;
    });
    // Bands: each thread owns its rows of the output.
    double* oz = out_z ? out_z + bi * HW : nullptr;
    const double* bfz = has_floor ? fz + bi * HW : nullptr;
    const int64_t* bfi = has_floor ? fi + bi * HW : nullptr;
    // Plain (one layer, no floor, no count: rasterize itself) is compiled
    // on its own, the per-fragment test without the branches of the other
    // modes.
    auto bands = [&](auto plain) {
      using Plain = decltype(plain);
      dynamic_for(nb, [&](auto&& next_band) {
        // Local copies of what the loops read: through the captured
        // references the compiler must assume that the id and depth stores
        // may change them, and reloaded them for every pixel.
        const int64_t Wl = W, Hl = H, Kl = K, Sl = S, HWl = HW, bil = bi;
        const bool countl = count, floorl = has_floor;
        const double *const xsl = xs.data(), *const ysl = ys.data(), *const bfzl = bfz;
        const int64_t *const startl = start.data(), *const bfil = bfi;
        const Live* const* const listl = list.get();
        double* const ozl = oz;
        int64_t* const* const layl = lay.data();
        int64_t* const oidl = lay[0] + bil * HWl;
        const Ctx cxl = cx;
        BandSink* const sinkl = sink;
        Exact e;
        Float fl;
        // The band's z-buffer (K > 1: k-buffer; a count: the counts) in
        // cache, written out at the end of the band: clearing the outputs
        // themselves first cost a second pass over them (and their page
        // faults, where the allocator had handed the memory back), more
        // than the rasterization of a small mesh's band. + 4: the four-
        // pixel loop's slack past the last column.
        const bool vec = Plain::value && simd_on();
        (void)vec;
        std::vector<double> kz(kBand * Wl * Kl + 4);
        std::vector<int64_t> ki(kBand * Wl * Kl + 4);
        for (int64_t band; (band = next_band()) >= 0;) {
          const int64_t R0 = band * kBand, R1 = std::min(Hl, R0 + kBand);
          // Pixel p's K entries start at zb / ib + (p - p0) * K.
          double* const zb = kz.data();
          int64_t* const ib = ki.data();
          const int64_t p0 = R0 * Wl;
          for (int64_t j = (R0 * Wl - p0) * Kl; j < (R1 * Wl - p0) * Kl; ++j) {
            zb[j] = INFINITY;
            ib[j] = countl ? 0 : kEmpty;
          }
          // One covered fragment (z in range): count it, or the depth test.
          auto frag = [&](int64_t p, double z, int64_t f) {
            if (!(z >= -1 && z <= 1)) return;
            if constexpr (Plain::value) {
              const int64_t q = p - p0;
              if (z < zb[q] || (z == zb[q] && f < ib[q])) {
                zb[q] = z;
                ib[q] = f;
              }
              return;
            }
            if (countl) {
              ++ib[p - p0];
              return;
            }
            if (floorl && !(z > bfzl[p] || (z == bfzl[p] && f > bfil[p]))) return;
            // The pixel's K nearest fragments so far in (depth, id) order (a
            // k-buffer; K = 1: the z-buffer): insert unless behind the K-th.
            double* zs = zb + (p - p0) * Kl;
            int64_t* is = ib + (p - p0) * Kl;
            int64_t k = Kl - 1;
            if (!(z < zs[k] || (z == zs[k] && f < is[k]))) return;
            for (; k > 0 && (z < zs[k - 1] || (z == zs[k - 1] && f < is[k - 1])); --k) {
              zs[k] = zs[k - 1];
              is[k] = is[k - 1];
            }
            zs[k] = z;
            is[k] = f;
          };
          for (int64_t li = startl[band]; li < startl[band + 1]; ++li) {
            // The corners' positions kAhead triangles ahead (the records
            // themselves are read in order).
            if (li + kAhead < startl[band + 1]) {
              const Live& a = *listl[li + kAhead];
              if (!(a.f & kFloatBit))
                for (int i = 0; i < 3; ++i) DT_PREFETCH(cxl.row(a.v[i]), false);
            }
            const Live& lv = *listl[li];
            const int64_t f = lv.f & ~kFloatBit;
            if (lv.x[2] == kDirect) {
              // Only the depth plane to set up, and the covered centres' depths.
              if (!exact_plane(cxl, lv.v, e)) continue;
              const int64_t nc = lv.x[1];
              for (int sl = 0; sl < int(kProbe); ++sl) {
                if (!(lv.y[1] >> sl & 1)) continue;
                const int64_t r = lv.y[0] + (nc == 1 ? sl : nc == 2 ? sl >> 1 : 0);
                const int64_t c = lv.x[0] + (nc == 1 ? 0 : nc == 2 ? sl & 1 : sl);
                if (r < R0 || r >= R1) continue;
                frag(r * Wl + c, (e.z0 + e.zx * (xsl[c] - e.x0)) + e.zy * (ysl[r] - e.y0), f);
              }
              continue;
            }
            if (!(lv.f & kFloatBit)) {
              for (int i = 0; i < 3; ++i) {
                e.x[i] = lv.x[i];
                e.y[i] = lv.y[i];
              }
              if (!exact_box(cxl, e) || !exact_edges(cxl, e) || !exact_plane(cxl, lv.v, e)) continue;
              const int64_t h = int64_t(1) << (Sl - 1), step = 2 * h;
              const int64_t r0 = std::max(e.r0, R0), r1 = std::min(e.r1, R1 - 1);
              const int64_t c0 = e.c0, c1 = e.c1, t0 = e.thr[0], t1 = e.thr[1], t2 = e.thr[2];
              const double z0 = e.z0, zx = e.zx, x0 = e.x0;
              const int64_t qx0 = (2 * e.c0 + 1 - Wl) * h;
              for (int64_t r = r0; r <= r1; ++r) {
                const int64_t qy = (2 * r + 1 - Hl) * h;
                int64_t E0 = e.a[0] * qx0 + e.c[0] + e.b[0] * qy;
                int64_t E1 = e.a[1] * qx0 + e.c[1] + e.b[1] * qy;
                int64_t E2 = e.a[2] * qx0 + e.c[2] + e.b[2] * qy;
                const int64_t s0 = e.a[0] * step, s1 = e.a[1] * step, s2 = e.a[2] * step;
                const double dy = e.zy * (ysl[r] - e.y0);
#if DT_HAVE_AVX2
                if (vec) {
                  // Wider boxes: first the row's span, as below.
                  int64_t lo = 0, hi = c1 - c0;
                  if (hi >= 8) {
                    row_span(E0, E1, E2, s0, s1, s2, e.thr, lo, hi);
                    if (lo > hi) continue;
                  }
                  const int64_t q = (r - R0) * Wl;
                  exact_row_avx2(zb + q, ib + q, xsl, c0 + lo, c0 + hi, E0 + s0 * lo, E1 + s1 * lo, E2 + s2 * lo, s0,
                                 s1, s2, t0, t1, t2, z0, zx, x0, dy, f);
                  continue;
                }
#endif
                if (c1 - c0 < 8) {
                  for (int64_t c = c0; c <= c1; ++c, E0 += s0, E1 += s1, E2 += s2) {
                    if (E0 >= t0 && E1 >= t1 && E2 >= t2) frag(r * Wl + c, (z0 + zx * (xsl[c] - x0)) + dy, f);
                  }
                  continue;
                }
                // Wider boxes: the row's span solved exactly per edge (E is
                // affine in the column, steps s_k), then no test per pixel.
                int64_t lo = 0, hi = c1 - c0;
                row_span(E0, E1, E2, s0, s1, s2, e.thr, lo, hi);
                for (int64_t c = c0 + lo; c <= c0 + hi; ++c) frag(r * Wl + c, (z0 + zx * (xsl[c] - x0)) + dy, f);
              }
            } else {
              setup_float(cxl, f, fl);
              const int64_t r0 = std::max(fl.r0, R0), r1 = std::min(fl.r1, R1 - 1);
              for (int64_t r = r0; r <= r1; ++r) {
                const double y = ysl[r];
                const double by0 = fl.b[0] * y, by1 = fl.b[1] * y, by2 = fl.b[2] * y, zy = fl.zc[1] * y;
                for (int64_t c = fl.c0; c <= fl.c1; ++c) {
                  const double x = xsl[c];
                  if ((fl.a[0] * x + fl.c[0]) + by0 >= fl.thr[0] && (fl.a[1] * x + fl.c[1]) + by1 >= fl.thr[1] &&
                      (fl.a[2] * x + fl.c[2]) + by2 >= fl.thr[2])
                    frag(r * Wl + c, (fl.zc[0] * x + fl.zc[2]) + zy, f);
                }
              }
            }
          }
          if (Kl > 1) {
            for (int64_t p = R0 * Wl; p < R1 * Wl; ++p) {
              const int64_t* is = ib + (p - p0) * Kl;
              for (int64_t k = 0; k < Kl; ++k) layl[k][bil * HWl + p] = is[k] == kEmpty ? -1 : is[k];
              if (ozl) ozl[p] = zb[(p - p0) * Kl + Kl - 1];
            }
            if (sinkl)
              for (int64_t k = 0; k < Kl; ++k) sinkl->band(layl[k], bil, R0, R1, k);
          } else if (countl) {
            std::memcpy(oidl + R0 * Wl, ib, sizeof(int64_t) * (R1 - R0) * Wl);
          } else {
            for (int64_t p = R0 * Wl; p < R1 * Wl; ++p) {
              const int64_t i = ib[p - p0];
              oidl[p] = i == kEmpty ? -1 : i;
            }
            if (ozl) std::memcpy(ozl + R0 * Wl, zb, sizeof(double) * (R1 - R0) * Wl);
            if (sinkl) sinkl->band(layl[0], bil, R0, R1, 0);
          }
        }
      });
    };
    if (K == 1 && !has_floor && !count)
      bands(std::true_type{});
    else
      bands(std::false_type{});
  }
  return {ids, depth};
}

}  // namespace

namespace {

// geometry/raster.py _bary_at for one triangle, in double whatever the
// input dtype (its float32 outputs are then rounded once, at the end).
// load() keeps the corners scaled by a power of two (max |coordinate| in
// [0.5, 1): no overflow, the same ratios); consecutive pixels of a row
// mostly share a triangle, so it runs once per run of them, with the
// slopes a_i = de_i/dx = Y_j W_k - W_j Y_k, b_i = de_i/dy = W_j X_k - X_j W_k
// (pixel-independent; from float32 corners both products are exact in
// double, so one rounding). Per pixel the corners are sheared to the
// pixel-centred frame X' = X - x W, Y' = Y - y W (determinant 1, the pixel
// moves to (0, 0, 1)): the edge functions e_i = det[h_j, h_k, p] =
// X'_j Y'_k - Y'_j X'_k are then products of small numbers on a small or
// distant triangle, where the expanded a x + b y + c cancels large terms
// (issue 40: barycentrics off by 1 on sub-pixel triangles).
struct Tri {
  double X[3], Y[3], Z[3], Wc[3], a[3], b[3], sa, sb, sc;

  template <typename T>
  void load(const T* pos, const int64_t* corner_rows) {
    double m = 0;
    for (int i = 0; i < 3; ++i) {
      const T* v = pos + 4 * corner_rows[i];
      X[i] = v[0], Y[i] = v[1], Z[i] = v[2], Wc[i] = v[3];
      m = std::max({m, std::abs(X[i]), std::abs(Y[i]), std::abs(Z[i]), std::abs(Wc[i])});
    }
    sc = pow2_scale(m);
    for (int i = 0; i < 3; ++i) X[i] *= sc, Y[i] *= sc, Z[i] *= sc, Wc[i] *= sc;
    for (int i = 0; i < 3; ++i) {
      const int j = (i + 1) % 3, k = (i + 2) % 3;
      a[i] = Y[j] * Wc[k] - Wc[j] * Y[k];
      b[i] = Wc[j] * X[k] - X[j] * Wc[k];
    }
    sa = a[0] + a[1] + a[2];
    sb = b[0] + b[1] + b[2];
  }

  // The sheared corners and the edge functions e at the NDC point (x, y).
  void edges(double x, double y, double* Xs, double* Ys, double* e) const {
    for (int i = 0; i < 3; ++i) Xs[i] = X[i] - x * Wc[i], Ys[i] = Y[i] - y * Wc[i];
    for (int i = 0; i < 3; ++i) {
      const int j = (i + 1) % 3, k = (i + 2) % 3;
      e[i] = Xs[j] * Ys[k] - Ys[j] * Xs[k];
    }
  }

  // Barycentrics ob, d/d(column) odx, d/d(row) ody [3] (null odx: no
  // derivatives) and the NDC depth at the NDC point (x, y); (sx, sy) =
  // (2 / W, -2 / H). Zeros where degenerate.
  template <typename T>
  T eval(double x, double y, double sx, double sy, T* ob, T* odx, T* ody) const {
    double Xs[3], Ys[3], e[3];
    edges(x, y, Xs, Ys, e);
    const double s = e[0] + e[1] + e[2];
    if (s == 0) {
      for (int i = 0; i < 3; ++i) ob[i] = 0;
      if (odx)
        for (int i = 0; i < 3; ++i) odx[i] = ody[i] = 0;
      return 0;
    }
    const double is = 1.0 / s;
    for (int i = 0; i < 3; ++i) ob[i] = T(e[i] * is);
    if (odx) {
      const double isx = is * sx, isy = is * sy;
      for (int i = 0; i < 3; ++i) {
        const double bi = e[i] * is;
        odx[i] = T((a[i] - bi * sa) * isx);
        ody[i] = T((b[i] - bi * sb) * isy);
      }
    }
    const double zn = e[0] * Z[0] + e[1] * Z[1] + e[2] * Z[2];
    const double wn = e[0] * Wc[0] + e[1] * Wc[1] + e[2] * Wc[2];
    return wn != 0 ? T(zn / wn) : T(0);
  }

  // The adjoint of eval (reverse mode by hand): gB, gDx, gDy [3] and gZ the
  // output gradients (null: none) -> g [12] the gradient w.r.t. the
  // unscaled corners (the outputs do not depend on the scale, so it is the
  // scaled corners' gradient times sc).
  template <typename T>
  void adjoint(double x, double y, double sx, double sy, const T* gB, const T* gDx, const T* gDy, const T* gZ,
               T* g) const {
    for (int i = 0; i < 12; ++i) g[i] = 0;
    double Xs[3], Ys[3], e[3];
    edges(x, y, Xs, Ys, e);
    const double s = e[0] + e[1] + e[2];
    if (s == 0) return;  // the outputs are the constant 0 there
    const double is = 1.0 / s;
    double ga[3], gb[3], ge[3];
    double gs = 0, gsa = 0, gsb = 0;
    for (int i = 0; i < 3; ++i) {
      const double bary = e[i] * is;
      double gbary = gB ? double(gB[i]) : 0.0;
      ga[i] = gb[i] = 0;
      if (gDx) {
        const double gd = gDx[i];
        const double dx = (a[i] - bary * sa) * is * sx;
        ga[i] += sx * gd * is;
        gsa -= sx * gd * bary * is;
        gbary -= sx * sa * gd * is;
        gs -= gd * dx * is;
      }
      if (gDy) {
        const double gd = gDy[i];
        const double dy = (b[i] - bary * sb) * is * sy;
        gb[i] += sy * gd * is;
        gsb -= sy * gd * bary * is;
        gbary -= sy * sb * gd * is;
        gs -= gd * dy * is;
      }
      ge[i] = gbary * is;
      gs -= gbary * bary * is;
    }
    double gXs[3] = {0, 0, 0}, gYs[3] = {0, 0, 0}, gX[3] = {0, 0, 0}, gY[3] = {0, 0, 0}, gZc[3] = {0, 0, 0},
           gW[3] = {0, 0, 0};
    if (gZ) {
      const double zn = e[0] * Z[0] + e[1] * Z[1] + e[2] * Z[2];
      const double wn = e[0] * Wc[0] + e[1] * Wc[1] + e[2] * Wc[2];
      if (wn != 0) {
        const double gzn = double(*gZ) / wn, gwn = -double(*gZ) * (zn / wn) / wn;
        for (int i = 0; i < 3; ++i) {
          ge[i] += gzn * Z[i] + gwn * Wc[i];
          gZc[i] = gzn * e[i];
          gW[i] = gwn * e[i];
        }
      }
    }
    for (int i = 0; i < 3; ++i) {
      const int j = (i + 1) % 3, k = (i + 2) % 3;
      const double gei = ge[i] + gs, gai = ga[i] + gsa, gbi = gb[i] + gsb;
      // e_i = Xs_j Ys_k - Ys_j Xs_k
      gXs[j] += gei * Ys[k], gYs[k] += gei * Xs[j], gYs[j] -= gei * Xs[k], gXs[k] -= gei * Ys[j];
      // a_i = Y_j W_k - W_j Y_k
      gY[j] += gai * Wc[k], gW[k] += gai * Y[j], gW[j] -= gai * Y[k], gY[k] -= gai * Wc[j];
      // b_i = W_j X_k - X_j W_k
      gW[j] += gbi * X[k], gX[k] += gbi * Wc[j], gX[j] -= gbi * Wc[k], gW[k] -= gbi * X[j];
    }
    for (int i = 0; i < 3; ++i) {
      // Xs = X - x W, Ys = Y - y W
      g[4 * i] = T((gX[i] + gXs[i]) * sc);
      g[4 * i + 1] = T((gY[i] + gYs[i]) * sc);
      g[4 * i + 2] = T(gZc[i] * sc);
      g[4 * i + 3] = T((gW[i] - x * gXs[i] - y * gYs[i]) * sc);
    }
  }
};

}  // namespace

// One thread's rows of raster_fragments' outputs: row(r, n) writes image
// row r (of all B * H) of the dense outputs from tri_id (pid), its covered
// pixels also in compact form from slot n on. o as raster_fragments' outputs
// after idx (packed: rast, db; else bary_c, dx_c, dy_c, bary, depth,
// bary_dx, bary_dy); the compact ones may point into a band's own buffers
// (the fused pass: n counts from 0 there).
template <typename T>
struct FragRows {
  const T* pp;
  const int64_t *pf, *pid;
  int64_t V, F, H, W;
  bool packed, derivatives;
  int64_t offset;
  T* const* o;
  int64_t* pidx;
  Tri tri{};  // value-initialised: gcc cannot see that load() runs before the first use
  int64_t loaded = -1;  // the (batch, face) in tri

  int64_t row(int64_t r, int64_t n) {
    T b[3] = {}, dx[3] = {}, dy[3] = {};
    // Pixel centres and scales in double, as the torch path's (_pixels).
    const double sx = 2.0 / double(W), sy = -2.0 / double(H);
    const double hx = 2.0 / double(W), hy = 2.0 / double(H);
    const int64_t bi = r / H, rw = r - bi * H;
    // _pixel_centres: (i + 0.5) * (2 / n) - 1, negated for rows.
    const double y = -((double(rw) + 0.5) * hy - 1.0);
    int64_t bg = r * W;  // the current background run is [bg, p)
    auto zero_run = [&](int64_t end) {
      if (end == bg) return;
      const size_t m = size_t(end - bg) * sizeof(T);
      if (packed) {
        std::memset(o[0] + 4 * bg, 0, 4 * m);
        if (derivatives) std::memset(o[1] + 4 * bg, 0, 4 * m);
      } else {
        std::memset(o[3] + 3 * bg, 0, 3 * m);
        if (derivatives)
          for (int k : {5, 6}) std::memset(o[k] + 3 * bg, 0, 3 * m);
        std::memset(o[4] + bg, 0, m);
      }
    };
    for (int64_t col = 0; col < W; ++col) {
      const int64_t p = r * W + col;
      const int64_t f = pid[p];
      if (f < 0) continue;  // background costs one test (most of a deep peeling layer)
      // Small triangles change every pixel: their face rows 2 kAhead
      // pixels ahead, then (those rows in cache) their corners.
      if (col + 2 * kAhead < W && pid[p + 2 * kAhead] >= 0) DT_PREFETCH(pf + 3 * pid[p + 2 * kAhead], false);
      if (col + kAhead < W && pid[p + kAhead] >= 0 && pid[p + kAhead] != pid[p + kAhead - 1]) {
        const int64_t* fa = pf + 3 * pid[p + kAhead];
        for (int i = 0; i < 3; ++i) DT_PREFETCH(pp + 4 * (bi * V + fa[i]), false);
      }
      zero_run(p);
      bg = p + 1;
      if (bi * F + f != loaded) {
        const int64_t rows3[3] = {bi * V + pf[3 * f], bi * V + pf[3 * f + 1], bi * V + pf[3 * f + 2]};
        tri.load(pp, rows3);
        loaded = bi * F + f;
      }
      const double x = (double(col) + 0.5) * hx - 1.0;
      const T z = tri.eval(x, y, sx, sy, b, derivatives ? dx : nullptr, dy);
      pidx[n] = p;
      if (packed) {
        T* ra = o[0] + 4 * p;
        ra[0] = b[0], ra[1] = b[1], ra[2] = z, ra[3] = T(f + 1 + offset);
        if (derivatives) {
          T* db = o[1] + 4 * p;
          db[0] = dx[0], db[1] = dy[0], db[2] = dx[1], db[3] = dy[1];
        }
      } else {
        for (int k = 0; k < 3; ++k) o[0][3 * n + k] = o[3][3 * p + k] = b[k];
        if (derivatives)
          for (int k = 0; k < 3; ++k) {
            o[1][3 * n + k] = o[5][3 * p + k] = dx[k];
            o[2][3 * n + k] = o[6][3 * p + k] = dy[k];
          }
        o[4][p] = z;
      }
      ++n;
    }
    zero_run((r + 1) * W);
    return n;
  }
};

// rasterize's differentiable pass, forward only (geometry/raster.py
// fragments_of; its torch formula gives the gradients). One threaded pass
// over the pixels of tri_id [B, H, W] (-1 background) writes the dense
// outputs, zeros on background, and the covered pixels in compact form
// (flat index order), so no nonzero / gather / scatter on the Python side.
std::vector<Tensor> raster_fragments(Tensor pos, Tensor faces, Tensor tri_id,
                                            bool packed, int64_t offset, bool derivatives) {
  DT_CHECK(pos.is_cpu() && pos.dim() == 3 && pos.size(2) == 4 && faces.dim() == 2 &&
                  faces.size(1) == 3 && faces.scalar_type() == kInt64 && tri_id.dim() == 3 &&
                  tri_id.scalar_type() == kInt64 && tri_id.size(0) == pos.size(0),
              "raster_fragments: expected pos [B, V, 4] float, faces [F, 3] int64, tri_id [B, H, W] int64 on the CPU");
  pos = contig(pos);
  faces = contig(faces);
  tri_id = contig(tri_id);
  const int64_t B = tri_id.size(0), H = tri_id.size(1), W = tri_id.size(2), V = pos.size(1), F = faces.size(0);
  const int64_t rows = B * H;
  const int64_t* pid = tri_id.mutable_data_ptr<int64_t>();
  const int64_t* pf = faces.mutable_data_ptr<int64_t>();
  // Covered pixels per image row, then their prefix: each row's first slot
  // in the compact outputs, so the rows can be filled in parallel.
  std::vector<int64_t> first(rows + 1, 0);
  parallel_for(0, rows, 64, [&](int64_t lo, int64_t hi) {
    for (int64_t r = lo; r < hi; ++r) {
      int64_t n = 0;
      for (int64_t c = 0; c < W; ++c) n += pid[r * W + c] >= 0;
      first[r + 1] = n;
    }
  });
  for (int64_t r = 0; r < rows; ++r) first[r + 1] += first[r];
  const int64_t N = first[rows];
  auto opt = options_of(pos);
  auto idx = empty({N}, options_of(tri_id));
  // Every byte of the dense outputs is written once: covered pixels by the
  // formula, background runs of a row by one memset per output (zeros
  // first and covered pixels after cost a second pass over the covered
  // ones, the bound of a mostly covered image).
  auto dense = [&](IntArrayRef shape, Options o) { return empty(shape, o); };
  std::vector<Tensor> out{idx};
  // Without derivatives their outputs are empty [0] tensors, never written.
  auto none = [&] { return empty({0}, opt); };
  if (packed) {
    out.push_back(dense({B, H, W, 4}, opt));  // rast: (b0, b1, depth, id + 1 + offset), 0 on background
    out.push_back(derivatives ? dense({B, H, W, 4}, opt) : none());  // db: (db0/dX, db0/dY, db1/dX, db1/dY)
  } else {
    out.push_back(empty({N, 3}, opt));  // compact bary, d/dcolumn, d/drow
    for (int k = 0; k < 2; ++k) out.push_back(derivatives ? empty({N, 3}, opt) : none());
    out.push_back(dense({B, H, W, 3}, opt));
    out.push_back(dense({B, H, W}, opt));
    for (int k = 0; k < 2; ++k) out.push_back(derivatives ? dense({B, H, W, 3}, opt) : none());
  }
  DT_DISPATCH_FLOATING_TYPES(pos.scalar_type(), "raster_fragments", [&] {
    using T = scalar_t;
    const T* pp = pos.mutable_data_ptr<T>();
    int64_t* pidx = idx.mutable_data_ptr<int64_t>();
    std::vector<T*> o;
    for (size_t i = 1; i < out.size(); ++i) o.push_back(out[i].mutable_data_ptr<T>());
    constexpr int64_t kRows = 8;  // rows an item
    dynamic_for((rows + kRows - 1) / kRows, [&](auto&& next_block) {
      FragRows<T> fr{pp, pf, pid, V, F, H, W, packed, derivatives, offset, o.data(), pidx};
      for (int64_t blk; (blk = next_block()) >= 0;)
        for (int64_t r = blk * kRows; r < std::min(rows, (blk + 1) * kRows); ++r) fr.row(r, first[r]);
    });
  });
  return out;
}

namespace {

// raster_fused's band work: the band's rows of the dense outputs, and its
// covered pixels in compact form in the band's own buffers (their global
// slots are known only once every band is done; the copy into place is
// one memcpy per band and output).
template <typename T>
struct FusedSink final : BandSink {
  const T* pp;
  const int64_t* pf;
  int64_t V, F, H, W, nb, nc;  // nc: chunks a layer (B * nb)
  bool derivatives;
  std::vector<T*> bary, depth, bdx, bdy;  // a layer each
  struct Chunk {
    int64_t n = 0;
    std::unique_ptr<int64_t[]> idx;
    std::unique_ptr<T[]> b, dx, dy;
  };
  std::vector<Chunk> chunks;  // [K, B * nb], batch-major: flat pixel order

  void band(const int64_t* all_ids, int64_t bi, int64_t R0, int64_t R1, int64_t k) override {
    Chunk& ch = chunks[k * nc + bi * nb + R0 / kBand];
    const int64_t r0 = bi * H + R0, r1 = bi * H + R1;
    int64_t n = 0;
    for (int64_t p = r0 * W; p < r1 * W; ++p) n += all_ids[p] >= 0;
    ch.n = n;
    ch.idx.reset(new int64_t[std::max<int64_t>(n, 1)]);
    ch.b.reset(new T[3 * std::max<int64_t>(n, 1)]);
    if (derivatives) {
      ch.dx.reset(new T[3 * std::max<int64_t>(n, 1)]);
      ch.dy.reset(new T[3 * std::max<int64_t>(n, 1)]);
    }
    T* const o[7] = {ch.b.get(), ch.dx.get(), ch.dy.get(), bary[k], depth[k], bdx[k], bdy[k]};
    FragRows<T> fr{pp, pf, all_ids, V, F, H, W, false, derivatives, 0, o, ch.idx.get()};
    int64_t m = 0;
    for (int64_t r = r0; r < r1; ++r) m = fr.row(r, m);
  }
};

}  // namespace

std::vector<Tensor> raster_fused(Tensor pos, Tensor faces, int64_t H, int64_t W, bool cull, int64_t bits,
                                 bool derivatives, bool keep_depth, int64_t layers) {
  DT_CHECK(pos.is_cpu() && (pos.scalar_type() == kFloat64 || pos.scalar_type() == kFloat32) && pos.dim() == 3 &&
               pos.size(2) == 4 && H > 0 && W > 0 && layers >= 1,
           "raster_fused: pos must be a CPU float32 or float64 tensor [B, V, 4], layers >= 1");
  pos = contig(pos);
  faces = contig(faces);
  const int64_t B = pos.size(0), V = pos.size(1), F = faces.size(0), nb = (H + kBand - 1) / kBand, K = layers;
  auto opt = options_of(pos);
  auto none = [&] { return empty({0}, opt); };
  // Every byte of the dense outputs is written by the bands (zeros on background).
  std::vector<Tensor> dense;  // per layer: bary, depth, bary_dx, bary_dy
  for (int64_t k = 0; k < K; ++k) {
    dense.push_back(empty({B, H, W, 3}, opt));
    dense.push_back(empty({B, H, W}, opt));
    for (int d = 0; d < 2; ++d) dense.push_back(derivatives ? empty({B, H, W, 3}, opt) : none());
  }
  std::vector<Tensor> out;
  DT_DISPATCH_FLOATING_TYPES(pos.scalar_type(), "raster_fused", [&] {
    using T = scalar_t;
    FusedSink<T> sink;
    sink.pp = pos.mutable_data_ptr<T>();
    sink.pf = faces.numel() ? faces.mutable_data_ptr<int64_t>() : nullptr;
    sink.V = V, sink.F = F, sink.H = H, sink.W = W, sink.nb = nb, sink.nc = B * nb, sink.derivatives = derivatives;
    for (int64_t k = 0; k < K; ++k) {
      sink.bary.push_back(dense[4 * k].mutable_data_ptr<T>());
      sink.depth.push_back(dense[4 * k + 1].mutable_data_ptr<T>());
      sink.bdx.push_back(derivatives ? dense[4 * k + 2].mutable_data_ptr<T>() : nullptr);
      sink.bdy.push_back(derivatives ? dense[4 * k + 3].mutable_data_ptr<T>() : nullptr);
    }
    sink.chunks.resize(K * B * nb);
    auto [ids, zbuf] = raster_impl(pos, faces, H, W, cull, bits, empty({0}, kFloat64), empty({0}, kInt64), false, K,
                                   &sink, keep_depth, true);
    if (ids[0].numel() == 0 && B * H * W > 0) {  // a non-finite position or a bad index: the caller names it
      out = {ids[0], zbuf};
      return;
    }
    out = ids;
    out.push_back(zbuf);
    const int64_t nc = B * nb;
    for (int64_t k = 0; k < K; ++k) {
      const auto* chunks = sink.chunks.data() + k * nc;
      std::vector<int64_t> at(nc + 1, 0);
      for (int64_t c = 0; c < nc; ++c) at[c + 1] = at[c] + chunks[c].n;
      const int64_t N = at[nc];
      Tensor idx = empty({N}, kInt64), bc = empty({N, 3}, opt);
      Tensor dxc = derivatives ? empty({N, 3}, opt) : none(), dyc = derivatives ? empty({N, 3}, opt) : none();
      int64_t* pidx = idx.mutable_data_ptr<int64_t>();
      T* pb = bc.mutable_data_ptr<T>();
      T* pdx = derivatives ? dxc.mutable_data_ptr<T>() : nullptr;
      T* pdy = derivatives ? dyc.mutable_data_ptr<T>() : nullptr;
      parallel_for(0, nc, 8, [&](int64_t lo, int64_t hi) {
        for (int64_t c = lo; c < hi; ++c) {
          const auto& ch = chunks[c];
          if (!ch.n) continue;
          std::memcpy(pidx + at[c], ch.idx.get(), sizeof(int64_t) * ch.n);
          std::memcpy(pb + 3 * at[c], ch.b.get(), sizeof(T) * 3 * ch.n);
          if (derivatives) {
            std::memcpy(pdx + 3 * at[c], ch.dx.get(), sizeof(T) * 3 * ch.n);
            std::memcpy(pdy + 3 * at[c], ch.dy.get(), sizeof(T) * 3 * ch.n);
          }
        }
      });
      for (const Tensor& t : {idx, bc, dxc, dyc}) out.push_back(t);
      for (int d = 0; d < 4; ++d) out.push_back(dense[4 * k + d]);
    }
  });
  return out;
}

// The first-order backward of raster_fragments, reading the output
// gradients where autograd left them (undefined: none): unpacked, grads =
// (bary, bary_dx, bary_dy [N, 3] compact; bary [B, H, W, 3], depth [B, H, W],
// bary_dx, bary_dy [B, H, W, 3] dense); packed, grads = (rast, db
// [B, H, W, 4]), rast's depth and id taking none. -> the gradient of pos
// [B, V, 4]. Threads accumulate into their own copy of it, summed at the
// end (no atomics; the order of the sums follows the thread split).
Tensor raster_fragments_backward(Tensor pos, Tensor faces, Tensor tri_id,
                                        Tensor idx, std::vector<Tensor> grads, bool packed) {
  DT_CHECK(pos.is_cpu() && pos.dim() == 3 && pos.size(2) == 4 && idx.scalar_type() == kInt64 &&
                  grads.size() == (packed ? 2u : 7u),
              "raster_fragments_backward: expected pos [B, V, 4] float, idx [N] int64 on the CPU and 7 (2 packed) "
              "gradients");
  pos = contig(pos);
  faces = contig(faces);
  tri_id = contig(tri_id);
  idx = contig(idx);
  for (auto& t : grads) {
    if (!t.defined() || t.numel() == 0) {
      t = Tensor();
      continue;
    }
    DT_CHECK(t.scalar_type() == pos.scalar_type(), "raster_fragments_backward: gradient dtype");
    t = contig(t);
  }
  const int64_t N = idx.size(0), H = tri_id.size(1), W = tri_id.size(2), V = pos.size(1);
  const int64_t threads = std::max<int64_t>(1, std::min<int64_t>(get_num_threads(), (N + 4095) / 4096));
  auto acc = zeros({threads, pos.numel()}, options_of(pos));
  DT_DISPATCH_FLOATING_TYPES(pos.scalar_type(), "raster_fragments_backward", [&] {
    using T = scalar_t;
    const T* pp = pos.mutable_data_ptr<T>();
    const int64_t* pf = faces.mutable_data_ptr<int64_t>();
    const int64_t* pid = tri_id.mutable_data_ptr<int64_t>();
    const int64_t* pidx = idx.mutable_data_ptr<int64_t>();
    std::vector<const T*> g;
    for (auto& t : grads) g.push_back(t.defined() ? t.mutable_data_ptr<T>() : nullptr);
    // Which of bary, depth, d/dcolumn, d/drow receive a gradient at all.
    const bool has_b = packed ? g[0] != nullptr : (g[0] || g[3]);
    const bool has_z = !packed && g[4];
    const bool has_dx = packed ? g[1] != nullptr : (g[1] || g[5]);
    const bool has_dy = packed ? g[1] != nullptr : (g[2] || g[6]);
    T* pacc = acc.mutable_data_ptr<T>();
    const double sx = 2.0 / double(W), sy = -2.0 / double(H);
    const double hx = 2.0 / double(W), hy = 2.0 / double(H);
    const int64_t chunk = (N + threads - 1) / threads;
    const int64_t F = faces.size(0);
    parallel_for(0, threads, 1, [&](int64_t lo, int64_t hi) {
      T gc[12], gB[3], gDx[3], gDy[3], gZ = 0;
      Tri tri{};  // value-initialised: gcc cannot see that load() runs before the first use
      for (int64_t t = lo; t < hi; ++t) {
        T* out = pacc + t * pos.numel();
        int64_t loaded = -1;
        for (int64_t n = t * chunk; n < std::min(N, (t + 1) * chunk); ++n) {
          const int64_t p = pidx[n];
          if (packed) {
            const T* r = g[0] ? g[0] + 4 * p : nullptr;
            const T* d = g[1] ? g[1] + 4 * p : nullptr;
            gB[0] = r ? r[0] : T(0), gB[1] = r ? r[1] : T(0), gB[2] = 0;
            gDx[0] = d ? d[0] : T(0), gDx[1] = d ? d[2] : T(0), gDx[2] = 0;
            gDy[0] = d ? d[1] : T(0), gDy[1] = d ? d[3] : T(0), gDy[2] = 0;
          } else {
            for (int k = 0; k < 3; ++k) {
              gB[k] = (g[0] ? g[0][3 * n + k] : T(0)) + (g[3] ? g[3][3 * p + k] : T(0));
              gDx[k] = (g[1] ? g[1][3 * n + k] : T(0)) + (g[5] ? g[5][3 * p + k] : T(0));
              gDy[k] = (g[2] ? g[2][3 * n + k] : T(0)) + (g[6] ? g[6][3 * p + k] : T(0));
            }
            gZ = g[4] ? g[4][p] : T(0);
          }
          const int64_t bi = p / (H * W), rc = p - bi * H * W, row = rc / W, col = rc - row * W;
          const int64_t f = pid[p];
          const int64_t rows3[3] = {bi * V + pf[3 * f], bi * V + pf[3 * f + 1], bi * V + pf[3 * f + 2]};
          if (bi * F + f != loaded) {
            tri.load(pp, rows3);
            loaded = bi * F + f;
          }
          const double x = (double(col) + 0.5) * hx - 1.0;
          const double y = -((double(row) + 0.5) * hy - 1.0);
          tri.adjoint(x, y, sx, sy, has_b ? gB : nullptr, has_dx ? gDx : nullptr, has_dy ? gDy : nullptr,
                      has_z ? &gZ : nullptr, gc);
          for (int i = 0; i < 3; ++i)
            for (int k = 0; k < 4; ++k) out[4 * rows3[i] + k] += gc[4 * i + k];
        }
      }
    });
  });
  return torch::stable::view(threads == 1 ? torch::stable::select(acc, 0, 0) : torch::stable::sum(acc, std::vector<int64_t>{0}), pos.sizes());
}

}  // namespace difftex
