// The single-level reads on the CPU: nearest, bilinear and bicubic
// (filters/separable.py SeparableSample), forward and first-order
// backward, one pass over the points, threaded over them. The semantics
// are those of the gather reference (filters/gather.py), which the tests
// hold it to: texel coordinate x = u * n - 0.5, nearest rounds x half to
// even, bilinear reads floor(x) and floor(x) + 1, bicubic floor(x) - 1 ..
// floor(x) + 2 with the Keys kernel (a = kCubicA, grid_sample's), every
// index wrapped per axis as wrap.py does.
//
// Bilinear and bicubic take u into one period in double (repeat: u - floor(u);
// mirror: reduce_coordinate's whole periods of 2, then the integer mirror of
// each tap, which keeps the reference's one-sided derivative at a texel
// centre): the same texels as the integer wrap. Nearest
// follows the reference step by step in the input's dtype
// (reduce_coordinate, then the rounding), so that a point on a texel edge
// rounds to the same side. Texel arithmetic is in the texture's dtype, with
// the channel count (1, 3, 4) and whether a border constant is read fixed
// at compile time (common.h specialized).
//
// The backward gives each point its uv gradient and scatters its texture
// gradient by bands of rows (bands.h): no lock, no per-thread texture
// copies, the same sums whatever the thread count.
#include "bands.h"
#include "common.h"
#include "kernels.h"

#if DT_HAVE_AVX2
#include <immintrin.h>
#endif

namespace difftex {
namespace {

enum Kind { NEAREST = 0, LINEAR = 1, CUBIC = 2 };

template <int KIND>
constexpr int taps_of() {
  return KIND == NEAREST ? 1 : (KIND == LINEAR ? 2 : 4);
}

// One axis of a read: K texel indices (and whether each is a texel rather
// than the border constant), their weights, d weight / d texel coordinate,
// and d(folded u) / du.
template <int K>
struct Line {
  int64_t i[K];
  bool in[K];
  double w[K], dw[K];
  double slope;
};

// Keys cubic convolution (gather.py _cubic_near / _cubic_far) and its
// derivative: near for |t| <= 1, far for 1 < |t| < 2.
DT_INLINE double cubic_near(double t) { return ((kCubicA + 2) * t - (kCubicA + 3)) * t * t + 1; }
DT_INLINE double cubic_near_d(double t) { return (3 * (kCubicA + 2) * t - 2 * (kCubicA + 3)) * t; }
DT_INLINE double cubic_far(double t) { return ((kCubicA * t - 5 * kCubicA) * t + 8 * kCubicA) * t - 4 * kCubicA; }
DT_INLINE double cubic_far_d(double t) { return (3 * kCubicA * t - 10 * kCubicA) * t + 8 * kCubicA; }

template <int KIND, typename scalar_t>
DT_INLINE Line<taps_of<KIND>()> line(scalar_t u, int64_t n, int mode) {
  Line<taps_of<KIND>()> a;
  if constexpr (KIND == NEAREST) {
    // gather.py reduce_coordinate, then round(u * n - 0.5), in scalar_t.
    scalar_t r = u;
    if (mode == REPEAT) {
      if (std::abs(u) >= 1) r = u - std::floor(u);
    } else if (mode == MIRROR) {
      if (std::abs(u) >= 2) r = u - 2 * std::floor(u / 2);
    } else {
      r = std::min(std::max(u, static_cast<scalar_t>(-kFarUv)), static_cast<scalar_t>(1 + kFarUv));
    }
    const scalar_t x = r * static_cast<scalar_t>(n) - static_cast<scalar_t>(0.5);
    // Half to even: x (|x| < 9n + 1) rounded in double by the 1.5 * 2^52 shift, which is exact for it.
    const double xd = static_cast<double>(x);
    const double xr = std::abs(xd) < 0.5 * kTwo52 ? (xd + 1.5 * kTwo52) - 1.5 * kTwo52 : xd;
    a.in[0] = wrap_int(index_of(xr), n, mode, &a.i[0]);
    a.w[0] = 1.0;
    a.dw[0] = 0.0;
    a.slope = 1.0;
  } else if constexpr (KIND == LINEAR) {
    const Axis ax = place(fold(static_cast<double>(u), mode), n, mode);
    a.i[0] = ax.i0; a.i[1] = ax.i1; a.in[0] = ax.in0; a.in[1] = ax.in1;
    a.w[0] = 1 - ax.f; a.w[1] = ax.f; a.dw[0] = -1; a.dw[1] = 1;
    a.slope = ax.slope;
  } else {
    const Folded fu = fold(static_cast<double>(u), mode);
    const double x = fu.u * static_cast<double>(n) - 0.5, x0 = floor_capped(x);
    const double t = std::abs(x) < kTwo52 ? x - x0 : 0.0;
    const int64_t i = static_cast<int64_t>(x0);
    for (int q = 0; q < 4; ++q) a.in[q] = wrap_int(i - 1 + q, n, mode, &a.i[q]);
    a.w[0] = cubic_far(t + 1); a.w[1] = cubic_near(t); a.w[2] = cubic_near(1 - t); a.w[3] = cubic_far(2 - t);
    a.dw[0] = cubic_far_d(t + 1); a.dw[1] = cubic_near_d(t); a.dw[2] = -cubic_near_d(1 - t);
    a.dw[3] = -cubic_far_d(2 - t);
    a.slope = fu.slope;
  }
  return a;
}

// The shapes and pointers of one call: texture [Bt, C, H, W], points
// p = b * M + e of uv [B, *S, 2], M = prod(S); per-point arrays [B, C, *S] (values,
// output gradients). The texture (and its gradient, allocated like it) is
// planar (contiguous) or interleaved (channels_last): texel (b, c, y, x) at
// b * image + c * cs + y * rs + x * xs. Interleaved, a bilinear read touches
// 2-4 cache lines instead of 2 per channel (measured on a 1024^2 RGB texture,
// 512^2 points: the forward's time follows the lines touched, not the
// arithmetic).
template <typename scalar_t>
struct Args {
  int64_t Bt, C, H, W, M, image, cs, rs, xs;
  int wrap_u, wrap_v;
  scalar_t border;
  const scalar_t* tex;
  const scalar_t* uv;
};

// Points go through the kernel in blocks of kBlock: first every point's
// taps along both axes (a loop without texel reads, which the compiler
// vectorises: measured, the per-point coordinate arithmetic and the serial
// texel-read latency made a one-point-at-a-time loop 6-8x slower than
// grid_sample's vectorised kernel), then the texel reads, a short body per
// point whose loads the CPU overlaps across points.
constexpr int kBlock = 64;

// One axis' taps of a block of points (structure of arrays).
template <int K>
struct Taps {
  int32_t i[K][kBlock];
  bool in[K][kBlock];
  double w[K][kBlock], dw[K][kBlock], slope[kBlock];
};

constexpr double kBig = 1073741824.0;  // 2^30: coordinates past it go through line() (int32 indices)

// floor(x) for |x| < 2^31, without a branch: a coordinate's fraction is
// random from point to point, and the compare-and-branch of common.h's
// floor_capped mispredicted half the time (measured: most of the kernel's
// time); selects also let the compiler vectorise the loop.
DT_INLINE double floor_near(double x) {
  const double t = static_cast<double>(static_cast<int32_t>(x));  // truncation toward 0
  return t - static_cast<double>(t > x);
}

// Bilinear / bicubic taps of cnt coordinates x[j] (finite, |x| < 2^30) along an axis of n texels, wrap MODE:
// the values of line() (the same fold, floor, wrap), in a loop of selects the compiler vectorises.
template <int KIND, int MODE>
void taps_near(const double* x, int cnt, int64_t n, Taps<taps_of<KIND>()>& T) {
  constexpr int K = taps_of<KIND>();
  const double nd = static_cast<double>(n);
  const int32_t ni = static_cast<int32_t>(n);
  for (int j = 0; j < cnt; ++j) {
    // Lanes past 2^30 (and NaN) are redone by line() afterwards; zero them here so that floor_near's int32
    // conversion never sees them (undefined behaviour, though its value was discarded).
    double u = std::abs(x[j]) < kBig ? x[j] : 0.0;
    if (MODE == REPEAT) {
      u = u - floor_near(u);
    } else if (MODE == MIRROR && std::fabs(u) >= 2.0) {
      // reduce_coordinate's whole periods only, and the integer mirror below: folding u itself would flip the side
      // of the one-sided derivative at a texel centre of a reflected copy (the reference takes it from the right
      // in u).
      u = u - 2.0 * floor_near(0.5 * u);
    }
    double c = u * nd - 0.5;
    if (MODE == CLAMP || MODE == BORDER) c = std::min(std::max(c, -kBig), kBig);
    const double c0 = floor_near(c), t = c - c0;
    const int32_t i = static_cast<int32_t>(c0);
    T.slope[j] = 1.0;
    for (int q = 0; q < K; ++q) {
      int32_t r = i + q - (K == 4 ? 1 : 0);
      bool in = true;
      if (MODE == REPEAT) {  // r in [-2, n + 1]: one period off at most (n = 1: clamped below)
        r += r < 0 ? ni : 0;
        r -= r >= ni ? ni : 0;
      } else if (MODE == MIRROR) {  // r in [-2n - 2, 2n + 1]: into one period 2n, the second copy reflected
        r += r < 0 ? 2 * ni : 0;
        r += r < 0 ? 2 * ni : 0;
        r -= r >= 2 * ni ? 2 * ni : 0;
        r = r >= ni ? 2 * ni - 1 - r : r;
      } else if (MODE == BORDER) {
        in = r >= 0 && r < ni;
      }
      r = r < 0 ? 0 : (r >= ni ? ni - 1 : r);  // clamp; a no-op for repeat / mirror from n = 2 on
      T.i[q][j] = r;
      T.in[q][j] = in;
    }
    if constexpr (KIND == LINEAR) {
      T.w[0][j] = 1.0 - t; T.w[1][j] = t; T.dw[0][j] = -1.0; T.dw[1][j] = 1.0;
    } else {
      T.w[0][j] = cubic_far(t + 1); T.w[1][j] = cubic_near(t); T.w[2][j] = cubic_near(1 - t);
      T.w[3][j] = cubic_far(2 - t);
      T.dw[0][j] = cubic_far_d(t + 1); T.dw[1][j] = cubic_near_d(t); T.dw[2][j] = -cubic_near_d(1 - t);
      T.dw[3][j] = -cubic_far_d(2 - t);
    }
  }
}

// The taps of a block's coordinates x[j] (from uv of dtype scalar_t) along an axis of n texels.
template <int KIND, typename scalar_t>
void taps_block(const double* x, int cnt, int64_t n, int mode, Taps<taps_of<KIND>()>& T) {
  constexpr int K = taps_of<KIND>();
  if constexpr (KIND != NEAREST) {
    switch (mode) {
      case REPEAT: taps_near<KIND, REPEAT>(x, cnt, n, T); break;
      case CLAMP: taps_near<KIND, CLAMP>(x, cnt, n, T); break;
      case MIRROR: taps_near<KIND, MIRROR>(x, cnt, n, T); break;
      default: taps_near<KIND, BORDER>(x, cnt, n, T);
    }
  }
  // Nearest, and the far or non-finite coordinates of the others: line(), one point at a time.
  for (int j = 0; j < cnt; ++j) {
    if (KIND != NEAREST && std::abs(x[j]) < kBig) continue;  // NaN fails the test too
    const auto a = line<KIND>(static_cast<scalar_t>(x[j]), n, mode);
    for (int q = 0; q < K; ++q) {
      const int64_t i = a.i[q];
      T.i[q][j] = static_cast<int32_t>(i);
      T.in[q][j] = a.in[q];
      T.w[q][j] = a.w[q];
      T.dw[q][j] = a.dw[q];
    }
    T.slope[j] = a.slope;
  }
}

// The first row point j of a block writes (its band's key): the wrapped
// first tap for repeat (its rows run on cyclically from there), else the
// least row read; -1 where every tap reads the border constant.
template <int K>
DT_INLINE int64_t first_row(const Taps<K>& T, int j, int mode) {
  if (mode == REPEAT) return T.i[0][j];
  int64_t r = -1;
  for (int q = 0; q < K; ++q)
    if (T.in[q][j] && (r < 0 || T.i[q][j] < r)) r = T.i[q][j];
  return r;
}

// The block's points: indices p into [B * M], their coordinates and
// whether both are finite.
template <typename scalar_t, int KIND>
struct Block {
  static constexpr int K = taps_of<KIND>();
  int cnt;
  int64_t p[kBlock];
  double u[kBlock], v[kBlock];
  bool ok[kBlock];
  Taps<K> x, y;

  void load(const scalar_t* uv, int64_t W, int64_t H, int wrap_u, int wrap_v) {
    for (int j = 0; j < cnt; ++j) {
      u[j] = static_cast<double>(uv[2 * p[j]]);
      v[j] = static_cast<double>(uv[2 * p[j] + 1]);
      ok[j] = std::isfinite(u[j]) && std::isfinite(v[j]);
    }
    taps_block<KIND, scalar_t>(u, cnt, W, wrap_u, x);
    taps_block<KIND, scalar_t>(v, cnt, H, wrap_v, y);
  }

  // Point j's taps, unpacked for its texel loop: weights, column and row
  // offsets (column times xs, row times rs).
  void point(int j, int64_t rs, int64_t xs, scalar_t* wx, scalar_t* wy, int64_t* cols, int64_t* rows) const {
    for (int q = 0; q < K; ++q) {
      wx[q] = static_cast<scalar_t>(x.w[q][j]);
      wy[q] = static_cast<scalar_t>(y.w[q][j]);
      cols[q] = x.i[q][j] * xs;
      rows[q] = y.i[q][j] * rs;
    }
  }
};

// Prefetches the texel rows of a block's points in the C channels of tex
// (write: for the gradient's scatter) before its loop reads them: the
// points of a view walk across the texture, so nearly every point needs
// lines that no cache holds, and one point's loads after another's left
// the loop waiting on memory latency (measured: 2-3x the time of the
// same loop over a texture in L1). Issued for the whole block at once,
// the misses overlap.

template <typename scalar_t, int KIND, bool kWrite>
DT_INLINE void prefetch_block(const Block<scalar_t, KIND>& bl, const scalar_t* tex, const Args<scalar_t>& A) {
  constexpr int K = taps_of<KIND>();
  // Interleaved: a texel's channels are adjacent, its first and last channel cover them.
  const int64_t step = A.cs == 1 ? std::max<int64_t>(A.C - 1, 1) : A.cs, C = A.cs == 1 ? std::min<int64_t>(A.C, 2) : A.C;
  for (int j = 0; j < bl.cnt; ++j) {
    if (!bl.ok[j]) continue;
    const int64_t b = A.Bt == 1 ? 0 : bl.p[j] / A.M;
    const scalar_t* t = tex + b * A.image;
    for (int r = 0; r < K; ++r) {
      const scalar_t* row = t + static_cast<int64_t>(bl.y.i[r][j]) * A.rs;
      for (int64_t c = 0; c < C; ++c) {
        DT_PREFETCH(row + c * step + bl.x.i[0][j] * A.xs, kWrite);
        if (K > 1) DT_PREFETCH(row + c * step + bl.x.i[K - 1][j] * A.xs, kWrite);
      }
    }
  }
}

template <typename scalar_t, int KIND, int CC, bool kBorder>
void forward_range(int64_t lo, int64_t hi, const Args<scalar_t>& A, scalar_t* out) {
  constexpr int K = taps_of<KIND>();
  const int64_t C = CC > 0 ? CC : A.C, M = A.M;
  Block<scalar_t, KIND> bl;
  for (int64_t s = lo; s < hi; s += kBlock) {
    bl.cnt = static_cast<int>(std::min<int64_t>(kBlock, hi - s));
    for (int j = 0; j < bl.cnt; ++j) bl.p[j] = s + j;
    bl.load(A.uv, A.W, A.H, A.wrap_u, A.wrap_v);
    prefetch_block<scalar_t, KIND, false>(bl, A.tex, A);
    int64_t b = s / M, e = s - b * M;
    for (int j = 0; j < bl.cnt; ++j, ++e) {
      if (e == M) e = 0, ++b;
      scalar_t* o = out + b * C * M + e;
      if (!bl.ok[j]) {
        for (int64_t c = 0; c < C; ++c) o[c * M] = std::numeric_limits<scalar_t>::quiet_NaN();
        continue;
      }
      const scalar_t* t = A.tex + (A.Bt == 1 ? 0 : b) * A.image;
      scalar_t wx[K], wy[K];
      int64_t cols[K], rows[K];
      bl.point(j, A.rs, A.xs, wx, wy, cols, rows);
      for (int64_t c = 0; c < C; ++c) {
        const scalar_t* tc = t + c * A.cs;
        scalar_t sum = 0;
        for (int r = 0; r < K; ++r) {
          const scalar_t* row = tc + rows[r];
          scalar_t acc = 0;
          for (int q = 0; q < K; ++q)
            acc += wx[q] * (!kBorder || (bl.y.in[r][j] && bl.x.in[q][j]) ? row[cols[q]] : A.border);
          sum += wy[r] * acc;
        }
        o[c * M] = sum;
      }
    }
  }
}

// The backward of a block's points: their uv gradients (guv not null) and
// texture gradients scattered into gt (not null).
template <typename scalar_t, int KIND, int CC, bool kBorder>
void backward_block(Block<scalar_t, KIND>& bl, const Args<scalar_t>& A, const scalar_t* grad, scalar_t* gt,
                    scalar_t* guv) {
  constexpr int K = taps_of<KIND>();
  const int64_t C = CC > 0 ? CC : A.C, M = A.M;
  bl.load(A.uv, A.W, A.H, A.wrap_u, A.wrap_v);
  if (guv != nullptr) prefetch_block<scalar_t, KIND, false>(bl, A.tex, A);
  if (gt != nullptr) prefetch_block<scalar_t, KIND, true>(bl, gt, A);
  for (int j = 0; j < bl.cnt; ++j) {
    if (!bl.ok[j]) continue;
    const int64_t p = bl.p[j], b = p / M, e = p - b * M;
    const scalar_t* g = grad + b * C * M + e;
    scalar_t wx[K], wy[K];
    int64_t cols[K], rows[K];
    bl.point(j, A.rs, A.xs, wx, wy, cols, rows);
    if (KIND != NEAREST && guv != nullptr) {
      const scalar_t* t = A.tex + (A.Bt == 1 ? 0 : b) * A.image;
      scalar_t dx[K], dy[K];
      for (int q = 0; q < K; ++q) dx[q] = static_cast<scalar_t>(bl.x.dw[q][j]), dy[q] = static_cast<scalar_t>(bl.y.dw[q][j]);
      scalar_t sx = 0, sy = 0;
      for (int64_t c = 0; c < C; ++c) {
        const scalar_t* tc = t + c * A.cs;
        scalar_t cx = 0, cy = 0;
        for (int r = 0; r < K; ++r) {
          const scalar_t* row = tc + rows[r];
          scalar_t rx = 0, rv = 0;
          for (int q = 0; q < K; ++q) {
            const scalar_t val = !kBorder || (bl.y.in[r][j] && bl.x.in[q][j]) ? row[cols[q]] : A.border;
            rx += dx[q] * val;
            rv += wx[q] * val;
          }
          cx += wy[r] * rx;
          cy += dy[r] * rv;
        }
        sx += g[c * M] * cx;
        sy += g[c * M] * cy;
      }
      guv[2 * p] = static_cast<scalar_t>(sx * bl.x.slope[j] * static_cast<double>(A.W));
      guv[2 * p + 1] = static_cast<scalar_t>(sy * bl.y.slope[j] * static_cast<double>(A.H));
    }
    if (gt != nullptr) {
      scalar_t* tg = gt + (A.Bt == 1 ? 0 : b) * A.image;
      for (int64_t c = 0; c < C; ++c) {
        const scalar_t gc = g[c * M];
        scalar_t* tc = tg + c * A.cs;
        for (int r = 0; r < K; ++r) {
          if (kBorder && !bl.y.in[r][j]) continue;
          scalar_t* row = tc + rows[r];
          const scalar_t gr = gc * wy[r];
          for (int q = 0; q < K; ++q)
            if (!kBorder || bl.x.in[q][j]) row[cols[q]] += gr * wx[q];
        }
      }
    }
  }
}

// ---------------------------------------------------------------------------
// The float32 bilinear / bicubic reads eight points at a time (AVX2), where
// the CPU has AVX2 and FMA (checked at run time; the scalar loops above
// serve elsewhere and for float64). Every float32 point goes through it,
// a tail group and the finite points of a group holding a non-finite one
// included (live lanes), so that how points fall into groups, which the
// thread count changes, changes no bit. Measured against the scalar loop: the per-point
// tap arithmetic and the one-texel-at-a-time loads were most of its time,
// even for a texture in L1 (3.9 of 7.5 ms for 512^2 points on 2 threads).
// Eight points' taps are computed in vector registers, each tap's texels
// of the eight points come in one gather, and a channel's eight results
// are one store into the planar output.
//
// The arithmetic is float32 throughout and follows the gather reference
// step by step (reduce_coordinate, x = u * n - 0.5 in the input's dtype,
// floor, the integer wrap of each tap), so both read the same texels with
// the same weights; clamp and border clip x to [-3, n + 2], where every
// tap is already off the texture on that side (the same texels, whatever
// the distance). Products and sums are not fused, so the blend rounds as
// the reference's does.
// ---------------------------------------------------------------------------
#if DT_HAVE_AVX2

// One axis of eight points: K tap indices (wrapped), whether each reads a
// texel (border: not the constant; all ones elsewhere), their weights and
// d weight / d texel coordinate. The integer wrap makes d x / du = n on
// every mode (no fold slope).
template <int K>
struct Axis8 {
  __m256i i[K], in[K];
  __m256 w[K], dw[K];
};

// The Keys cubic (cubic_near / cubic_far above) of eight points in float32, by Horner's scheme as the
// reference evaluates it.
constexpr float kA = static_cast<float>(kCubicA);
DT_AVX2 __m256 near8(__m256 s) {  // ((A + 2) s - (A + 3)) s s + 1
  const __m256 p = _mm256_sub_ps(_mm256_mul_ps(_mm256_set1_ps(kA + 2), s), _mm256_set1_ps(kA + 3));
  return _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(p, s), s), _mm256_set1_ps(1.0f));
}
DT_AVX2 __m256 near_d8(__m256 s) {  // (3 (A + 2) s - 2 (A + 3)) s
  return _mm256_mul_ps(_mm256_sub_ps(_mm256_mul_ps(_mm256_set1_ps(3 * (kA + 2)), s), _mm256_set1_ps(2 * (kA + 3))), s);
}
DT_AVX2 __m256 far8(__m256 s) {  // ((A s - 5A) s + 8A) s - 4A
  __m256 p = _mm256_sub_ps(_mm256_mul_ps(_mm256_set1_ps(kA), s), _mm256_set1_ps(5 * kA));
  p = _mm256_add_ps(_mm256_mul_ps(p, s), _mm256_set1_ps(8 * kA));
  return _mm256_sub_ps(_mm256_mul_ps(p, s), _mm256_set1_ps(4 * kA));
}
DT_AVX2 __m256 far_d8(__m256 s) {  // (3A s - 10A) s + 8A
  const __m256 p = _mm256_sub_ps(_mm256_mul_ps(_mm256_set1_ps(3 * kA), s), _mm256_set1_ps(10 * kA));
  return _mm256_add_ps(_mm256_mul_ps(p, s), _mm256_set1_ps(8 * kA));
}

template <int K>
DT_AVX2 void axis8(__m256 u, int32_t n, int mode, Axis8<K>& a) {
  const __m256 one = _mm256_set1_ps(1.0f), half = _mm256_set1_ps(0.5f), nf = _mm256_set1_ps(static_cast<float>(n));
  if (mode == REPEAT || mode == MIRROR) {  // reduce_coordinate: whole periods off where |u| >= one period
    const __m256 p = _mm256_set1_ps(mode == REPEAT ? 1.0f : 2.0f), inv = _mm256_set1_ps(mode == REPEAT ? 1.0f : 0.5f);
    const __m256 r = _mm256_sub_ps(u, _mm256_mul_ps(p, _mm256_floor_ps(_mm256_mul_ps(u, inv))));  // u / p exactly
    u = _mm256_blendv_ps(u, r, _mm256_cmp_ps(_mm256_andnot_ps(_mm256_set1_ps(-0.0f), u), p, _CMP_GE_OQ));
  }
  __m256 x = _mm256_sub_ps(_mm256_mul_ps(u, nf), half);
  if (mode == CLAMP || mode == BORDER)
    x = _mm256_min_ps(_mm256_max_ps(x, _mm256_set1_ps(-3.0f)), _mm256_add_ps(nf, _mm256_set1_ps(2.0f)));
  const __m256 x0 = _mm256_floor_ps(x), t = _mm256_sub_ps(x, x0);
  const __m256i i = _mm256_cvttps_epi32(x0), ni = _mm256_set1_epi32(n), zero = _mm256_setzero_si256();
  const __m256i last = _mm256_set1_epi32(n - 1), all = _mm256_set1_epi32(-1);
  for (int q = 0; q < K; ++q) {
    __m256i r = _mm256_add_epi32(i, _mm256_set1_epi32(q - (K == 4 ? 1 : 0)));
    __m256i in = all;
    const __m256i below = _mm256_cmpgt_epi32(zero, r);
    if (mode == REPEAT || mode == MIRROR) {  // r in [-P - 2, P + 1] for the period P = n (repeat), 2n (mirror)
      const __m256i P = mode == REPEAT ? ni : _mm256_add_epi32(ni, ni);
      r = _mm256_add_epi32(r, _mm256_and_si256(below, P));
      r = _mm256_add_epi32(r, _mm256_and_si256(_mm256_cmpgt_epi32(zero, r), P));
      r = _mm256_sub_epi32(r, _mm256_andnot_si256(_mm256_cmpgt_epi32(P, r), P));
      if (mode == MIRROR)  // the second copy reflected
        r = _mm256_blendv_epi8(_mm256_sub_epi32(_mm256_set1_epi32(2 * n - 1), r), r, _mm256_cmpgt_epi32(ni, r));
    } else if (mode == BORDER) {
      in = _mm256_andnot_si256(_mm256_or_si256(below, _mm256_cmpgt_epi32(r, last)), all);
    }
    a.i[q] = _mm256_min_epi32(_mm256_max_epi32(r, zero), last);
    a.in[q] = in;
  }
  if constexpr (K == 2) {
    a.w[0] = _mm256_sub_ps(one, t); a.w[1] = t;
    a.dw[0] = _mm256_set1_ps(-1.0f); a.dw[1] = one;
  } else {
    const __m256 t1 = _mm256_add_ps(t, one), s1 = _mm256_sub_ps(one, t), s2 = _mm256_sub_ps(_mm256_set1_ps(2.0f), t);
    a.w[0] = far8(t1); a.w[1] = near8(t); a.w[2] = near8(s1); a.w[3] = far8(s2);
    const __m256 neg = _mm256_set1_ps(-0.0f);
    a.dw[0] = far_d8(t1); a.dw[1] = near_d8(t);
    a.dw[2] = _mm256_xor_ps(near_d8(s1), neg); a.dw[3] = _mm256_xor_ps(far_d8(s2), neg);
  }
}

// Lanes whose u and v are both finite, as a bit mask (x - x is 0 for finite x, NaN for inf and NaN).
DT_AVX2 int finite_lanes(__m256 u, __m256 v) {
  const __m256 z = _mm256_add_ps(_mm256_sub_ps(u, u), _mm256_sub_ps(v, v));
  return _mm256_movemask_ps(_mm256_cmp_ps(z, _mm256_setzero_ps(), _CMP_EQ_OQ));
}

// The live lanes of a group of cnt <= 8 points: finite and below cnt. The other lanes' coordinates become 0.5,
// which any texture reads, and nothing of them is written: every point goes through the same arithmetic
// however the points fall into groups (a thread's share, a run of bands), so results do not depend on the
// thread count.
DT_AVX2 int live_lanes(int cnt, __m256& u, __m256& v) {
  const int live = finite_lanes(u, v) & ((1 << cnt) - 1);
  if (live != 0xFF) {
    const __m256 keep = _mm256_castsi256_ps(_mm256_cmpgt_epi32(
        _mm256_and_si256(_mm256_set1_epi32(live), _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128)),
        _mm256_setzero_si256()));
    u = _mm256_blendv_ps(_mm256_set1_ps(0.5f), u, keep);
    v = _mm256_blendv_ps(_mm256_set1_ps(0.5f), v, keep);
  }
  return live;
}

// Eight points' (u, v) from interleaved uv (cnt < 8: the first cnt, the rest padded); their live lanes.
DT_AVX2 int load8(const float* uv, int cnt, __m256& u, __m256& v) {
  alignas(32) float pad[16];
  if (cnt < 8) {
    for (int j = 0; j < 16; ++j) pad[j] = j < 2 * cnt ? uv[j] : 0.5f;
    uv = pad;
  }
  const __m256 a = _mm256_loadu_ps(uv), b = _mm256_loadu_ps(uv + 8);
  u = _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(_mm256_shuffle_ps(a, b, 0x88)), 0xD8));
  v = _mm256_castpd_ps(_mm256_permute4x64_pd(_mm256_castps_pd(_mm256_shuffle_ps(a, b, 0xDD)), 0xD8));
  return live_lanes(cnt, u, v);
}

// A group of eight points ready to read: both axes' taps and the taps' row and column offsets (row times
// rs, column times xs). cnt: its points (8 but at a tail); live: the lanes it writes (live_lanes).
template <int K>
struct Group8 {
  Axis8<K> ax, ay;
  __m256i rows[K], cols[K];
  int cnt, live;
  const float* tex;  // the forward's: its batch entry's texture and output offset (group_start)
  int64_t at;
};

template <int K>
DT_AVX2 void prepare8(const Args<float>& A, __m256 u, __m256 v, Group8<K>& g) {
  axis8<K>(u, static_cast<int32_t>(A.W), A.wrap_u, g.ax);
  axis8<K>(v, static_cast<int32_t>(A.H), A.wrap_v, g.ay);
  const __m256i rs = _mm256_set1_epi32(static_cast<int32_t>(A.rs)), xs = _mm256_set1_epi32(static_cast<int32_t>(A.xs));
  for (int r = 0; r < K; ++r) {
    g.rows[r] = _mm256_mullo_epi32(g.ay.i[r], rs);
    g.cols[r] = A.xs == 1 ? g.ax.i[r] : _mm256_mullo_epi32(g.ax.i[r], xs);
  }
}

// Prefetches the lines of N points' taps in C channels from base (kWrite: to write them, the texture
// gradient), given their first taps' offsets o[r][j] (row r, point j), as prefetch_block does for the scalar
// loop: a block's groups are prepared and prefetched first, then read, so that their misses overlap
// (measured: the backward without it waited on memory for most of its time).
//
// Only every fourth point's lines and the last point's: a group's neighbouring points mostly share lines,
// and a prefetch for every point cost more than the misses it saved. Measured (1024^2 RGB texture, 512^2
// points of a rotated view, 2.6 texels a point, 2 threads, in one process with and without): the bicubic
// forward in 0.81-0.87x the time planar and 0.92x channels_last in a loop (0.86-0.88x planar after a 30 ms
// pause), the channels_last bilinear forward 0.95x; forward+backward 0.96x bilinear and 0.91x bicubic in a
// loop, 0.97-1.01x after a pause. With the view minified 4x further (10 texels a point, points four apart
// on different lines) the forwards took 0.93-1.00x (channels_last bicubic 0.60x), forward+backward 0.99x.
template <int K, int N, bool kWrite>
inline __attribute__((always_inline)) void prefetch_rows(const int32_t (*o)[N], const float* base,
                                                         const Args<float>& A) {
  static_assert(N % 4 == 0, "the last point is not one of every fourth");
  const auto point = [&](int j) __attribute__((always_inline)) {
    if (A.cs == 1) {  // interleaved: a row's taps are K texels of C adjacent floats (unless they wrap)
      const int64_t last = K * A.C - 1;
      for (int r = 0; r < K; ++r) {
        DT_PREFETCH(base + o[r][j], kWrite);
        DT_PREFETCH(base + o[r][j] + last, kWrite);
      }
      return;
    }
    for (int r = 0; r < K; ++r)
      for (int64_t c = 0; c < A.C; ++c) DT_PREFETCH(base + c * A.cs + o[r][j], kWrite);
  };
  for (int j = 0; j < N; j += 4) point(j);
  point(N - 1);
}

// prefetch_rows of a group of eight.
template <int K, bool kWrite>
DT_AVX2 void prefetch8(const Group8<K>& g, const float* base, const Args<float>& A) {
  alignas(32) int32_t o[K][8];
  for (int r = 0; r < K; ++r)
    _mm256_store_si256(reinterpret_cast<__m256i*>(o[r]), _mm256_add_epi32(g.rows[r], g.cols[0]));
  prefetch_rows<K, 8, kWrite>(o, base, A);
}

// Texels of tap (r, q) of a group in one channel (its first value at chan); border taps read the constant.
template <bool kBorder, int K>
DT_AVX2 __m256 texels8(const float* chan, const Group8<K>& g, int r, int q, __m256 border) {
  const __m256i idx = _mm256_add_epi32(g.rows[r], g.cols[q]);
  if (!kBorder) return _mm256_i32gather_ps(chan, idx, 4);
  const __m256 m = _mm256_castsi256_ps(_mm256_and_si256(g.ay.in[r], g.ax.in[q]));
  return _mm256_mask_i32gather_ps(border, chan, idx, m, 4);
}

// The forward of a group from its texture into o[c * M] (c < C).
template <int K, int CC, bool kBorder>
DT_AVX2 void forward8(const Args<float>& A, const Group8<K>& g, float* o, int64_t M) {
  const int64_t C = CC > 0 ? CC : A.C;
  const float* tex = g.tex;
  const __m256 border = _mm256_set1_ps(A.border);
  for (int64_t c = 0; c < C; ++c) {
    const float* chan = tex + c * A.cs;
    __m256 sum = _mm256_setzero_ps();
    for (int r = 0; r < K; ++r) {
      __m256 acc = _mm256_setzero_ps();
      for (int q = 0; q < K; ++q)
        acc = _mm256_add_ps(acc, _mm256_mul_ps(g.ax.w[q], texels8<kBorder>(chan, g, r, q, border)));
      sum = _mm256_add_ps(sum, _mm256_mul_ps(g.ay.w[r], acc));
    }
    if (g.live == 0xFF) {
      _mm256_storeu_ps(o + c * M, sum);
      continue;
    }
    alignas(32) float part[8];
    _mm256_store_ps(part, sum);
    for (int j = 0; j < g.cnt; ++j)  // a non-finite coordinate reads NaN
      o[c * M + j] = g.live >> j & 1 ? part[j] : std::numeric_limits<float>::quiet_NaN();
  }
}

constexpr int kGroups = kBlock / 8;  // groups of a block

// The order in which the vector forwards read the points: where the pixel shape S is 2-D or more (rows of
// S[-1] >= kTileCols points), tiles of kTileRows rows by kTileCols points, row after row within a tile, tile
// after tile along the rows; else the points in order. Neighbouring pixels read neighbouring texels in both
// directions, so a tile's lines are still in L1 when the next row of the tile reads them (measured on a
// 1024^2 RGB texture, 512^2 points of a rotated view: 0.82-0.87x the time of reading the points in order,
// planar and channels_last). Segments are runs of up to kTileCols points of one row.
constexpr int64_t kTileRows = 8, kTileCols = 32;

struct Tiles {
  int64_t M, width, rows, cols;  // points per batch entry, row length, rows per entry, segments per row
  Tiles(const Args<float>& A, const Tensor& uv) : M(A.M) {
    width = uv.dim() >= 4 ? uv.size(-2) : M;
    if (width < kTileCols || width == M) width = M;
    rows = width > 0 ? M / width : 0;
    cols = (width + kTileCols - 1) / kTileCols;
  }
  int64_t count(int64_t B) const { return B * rows * cols; }
  // How far ahead in memory the uv of a point one tile later in reading order lies: the next tile's point on
  // the same row, or a tile's worth of points when the points are read in order. The hardware prefetcher
  // alone left the forward waiting on the uv stream (5-7% of it, same case).
  int64_t uv_lead() const { return rows > 1 ? kTileCols : kTileRows * kTileCols; }
};

// Walks the segments [s, end) of tiles in groups of up to N points. Segment s is batch entry b's band of
// rows, tile column xt, row yo of the band's h: the first one decoded with divisions, each next one by
// counting (the divisions of every segment were 4% of a bilinear forward, perf).
struct Walk {
  const Tiles& t;
  int64_t s, end;
  int64_t pos = 0, stop = 0;  // the current segment's points [pos, stop)
  int64_t b = 0, band = 0, xt = 0, yo = -1, h = 0;
  Walk(const Tiles& t_, int64_t lo, int64_t hi) : t(t_), s(lo), end(hi) {
    if (s >= end) return;
    const int64_t per_band = kTileRows * t.cols, e = s % (t.rows * t.cols);
    b = s / (t.rows * t.cols);
    band = e / per_band;
    h = std::min(kTileRows, t.rows - band * kTileRows);  // the last band may be short
    xt = e % per_band / h;
    yo = e % per_band % h - 1;  // next() steps onto it
  }
  bool next(int N, int64_t& first, int& cnt) {
    while (pos == stop) {
      if (s == end) return false;
      ++s;
      if (++yo == h) {
        yo = 0;
        if (++xt == t.cols) {
          xt = 0;
          if (++band * kTileRows >= t.rows) band = 0, ++b;
          h = std::min(kTileRows, t.rows - band * kTileRows);
        }
      }
      const int64_t x = xt * kTileCols;
      pos = b * t.M + (band * kTileRows + yo) * t.width + x;
      stop = pos + std::min(kTileCols, t.width - x);
    }
    first = pos;
    cnt = static_cast<int>(std::min<int64_t>(N, stop - pos));
    pos += cnt;
    return true;
  }
};

// A group's texture (its batch entry's) and offset in the output [B, C, M]; prefetches the uv lines (one or
// two) of the points a tile ahead of it.
inline const float* group_start(const Args<float>& A, const Walk& w, int64_t first, int64_t C, int lines,
                                int64_t& at) {
  const Tiles& t = w.t;
  const int64_t b = w.b;
  at = first + b * (C - 1) * A.M;
  if (first + t.uv_lead() < (b + 1) * A.M)
    for (int l = 0; l < lines; ++l) DT_PREFETCH(A.uv + 2 * (first + t.uv_lead()) + 16 * l, false);
  return A.tex + (A.Bt == 1 ? 0 : b) * A.image;
}

// Whether the vector forwards prefetch a group's texel lines as they prepare it: all but a planar bilinear
// read, whose 2 x C rows a point are streams the hardware prefetcher follows; a prefetch for each cost more
// than it saved. Measured (1024^2 RGB texture, 512^2 points of a rotated view, float32 clamp, with and
// without in one process): in a loop of calls (the texture in L3) 0.63-0.76x the time on the sixteen-point
// path (two threads; 0.59x on one), 0.71-0.83x on the eight-point one; with the caches flushed by 1 GB
// written between calls 1.00-1.01x and 1.08x. Planar bicubic and channels_last reads keep it: flushed
// (0.25-1 GB), they took 1.54x and 1.33-1.36x the time without it, and in a loop 0.93-1.01x and 0.89-1.02x.
template <int K>
DT_INLINE bool forward_prefetch(const Args<float>& A) { return K > 2 || A.cs == 1; }

// Prepares the next block of groups of eight points from the walk and prefetches their lines. Returns the
// group count (0 at the walk's end).
template <int K>
DT_AVX2 int prepare_block(const Args<float>& A, int64_t C, Walk& w, Group8<K>* grp) {
  int n = 0;
  for (int64_t first; n < kGroups && w.next(8, first, grp[n].cnt); ++n) {
    Group8<K>& g = grp[n];
    __m256 u, v;
    g.tex = group_start(A, w, first, C, 1, g.at);
    g.live = load8(A.uv + 2 * first, g.cnt, u, v);
    prepare8<K>(A, u, v, g);
    if (forward_prefetch<K>(A)) prefetch8<K, false>(g, g.tex, A);
  }
  return n;
}

// forward_range of the points of the tiles' segments [lo, hi), by blocks of groups of eight.
template <int KIND, int CC, bool kBorder>
__attribute__((target("avx2,fma"))) void forward_range_avx2(int64_t lo, int64_t hi, const Args<float>& A,
                                                            const Tiles& t, float* out) {
  constexpr int K = taps_of<KIND>();
  const int64_t C = CC > 0 ? CC : A.C;
  Walk w{t, lo, hi};
  in_two_blocks<Group8<K>, kGroups>(
      [&](Group8<K>* b) __attribute__((target("avx2,fma"))) { return prepare_block<K>(A, C, w, b); },
      [&](const Group8<K>& g) __attribute__((target("avx2,fma"))) {
        forward8<K, CC, kBorder>(A, g, out + g.at, A.M);
      });
}

// ---------------------------------------------------------------------------
// The float32 bilinear / bicubic forward sixteen points at a time (AVX-512,
// where the CPU has AVX512F and AVX512DQ, checked at run time; set_wide).
// The same arithmetic as the eight-point path above, operation for
// operation in each lane, so both give the same bits, with half the
// instructions a point for the taps, the weights and the blend. Measured on
// a 1024^2 RGB texture, 512^2 points, 2 threads, in rounds with the eight-
// point path: 0.77-0.80x its time for bilinear (channels_last and planar),
// 0.79-0.89x for bicubic. A row's taps are read as runs of 64-bit pairs of
// floats where they allow (pair_taps16; planar, and 3 or 4 interleaved
// channels), with the same texels and arithmetic. The backward
// stays on the eight-point path: its scatter adds one point after another
// anyway.
// ---------------------------------------------------------------------------
#define DT_AVX512 __attribute__((target("avx512f,avx512dq,avx2,fma"), always_inline)) inline

template <int K>
struct Axis16 {
  __m512i i[K];
  __mmask16 in[K];
  __m512 w[K];
};

DT_AVX512 __m512 near16(__m512 s) {
  const __m512 p = _mm512_sub_ps(_mm512_mul_ps(_mm512_set1_ps(kA + 2), s), _mm512_set1_ps(kA + 3));
  return _mm512_add_ps(_mm512_mul_ps(_mm512_mul_ps(p, s), s), _mm512_set1_ps(1.0f));
}
DT_AVX512 __m512 far16(__m512 s) {
  __m512 p = _mm512_sub_ps(_mm512_mul_ps(_mm512_set1_ps(kA), s), _mm512_set1_ps(5 * kA));
  p = _mm512_add_ps(_mm512_mul_ps(p, s), _mm512_set1_ps(8 * kA));
  return _mm512_sub_ps(_mm512_mul_ps(p, s), _mm512_set1_ps(4 * kA));
}

template <int K>
DT_AVX512 void axis16(__m512 u, int32_t n, int mode, Axis16<K>& a) {
  const __m512 one = _mm512_set1_ps(1.0f), half = _mm512_set1_ps(0.5f), nf = _mm512_set1_ps(static_cast<float>(n));
  constexpr int kFloor = _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC;
  if (mode == REPEAT || mode == MIRROR) {
    const __m512 p = _mm512_set1_ps(mode == REPEAT ? 1.0f : 2.0f), inv = _mm512_set1_ps(mode == REPEAT ? 1.0f : 0.5f);
    const __m512 r = _mm512_sub_ps(u, _mm512_mul_ps(p, _mm512_roundscale_ps(_mm512_mul_ps(u, inv), kFloor)));
    u = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(_mm512_abs_ps(u), p, _CMP_GE_OQ), u, r);
  }
  __m512 x = _mm512_sub_ps(_mm512_mul_ps(u, nf), half);
  if (mode == CLAMP || mode == BORDER)
    x = _mm512_min_ps(_mm512_max_ps(x, _mm512_set1_ps(-3.0f)), _mm512_add_ps(nf, _mm512_set1_ps(2.0f)));
  const __m512 x0 = _mm512_roundscale_ps(x, kFloor), t = _mm512_sub_ps(x, x0);
  const __m512i i = _mm512_cvttps_epi32(x0), ni = _mm512_set1_epi32(n), zero = _mm512_setzero_si512();
  const __m512i last = _mm512_set1_epi32(n - 1);
  for (int q = 0; q < K; ++q) {
    __m512i r = _mm512_add_epi32(i, _mm512_set1_epi32(q - (K == 4 ? 1 : 0)));
    __mmask16 in = 0xFFFF;
    const __mmask16 below = _mm512_cmpgt_epi32_mask(zero, r);
    if (mode == REPEAT || mode == MIRROR) {
      const __m512i P = mode == REPEAT ? ni : _mm512_add_epi32(ni, ni);
      r = _mm512_mask_add_epi32(r, below, r, P);
      r = _mm512_mask_add_epi32(r, _mm512_cmpgt_epi32_mask(zero, r), r, P);
      r = _mm512_mask_sub_epi32(r, _mm512_cmpge_epi32_mask(r, P), r, P);
      if (mode == MIRROR) {  // the second copy reflected
        const __m512i reflected = _mm512_sub_epi32(_mm512_set1_epi32(2 * n - 1), r);
        r = _mm512_mask_blend_epi32(_mm512_cmpgt_epi32_mask(ni, r), reflected, r);
      }
    } else if (mode == BORDER) {
      in = static_cast<__mmask16>(~(below | _mm512_cmpgt_epi32_mask(r, last)));
    }
    a.i[q] = _mm512_min_epi32(_mm512_max_epi32(r, zero), last);
    a.in[q] = in;
  }
  if constexpr (K == 2) {
    a.w[0] = _mm512_sub_ps(one, t); a.w[1] = t;
  } else {
    const __m512 t1 = _mm512_add_ps(t, one), s1 = _mm512_sub_ps(one, t), s2 = _mm512_sub_ps(_mm512_set1_ps(2.0f), t);
    a.w[0] = far16(t1); a.w[1] = near16(t); a.w[2] = near16(s1); a.w[3] = far16(s2);
  }
}

template <int K>
struct Group16 {
  Axis16<K> ax, ay;
  __m512i rows[K], cols[K];
  int cnt;
  __mmask16 live;
  // pair_taps16: paired, the K taps of a row lie in every lane within the K texels from column cols[0] on
  // (interior: tap q is texel q of them, else texel 2 * upper[q] + odd[q]).
  bool paired, interior;
  __mmask16 odd[K], upper[K];
  const float* tex;  // as Group8's
  int64_t at;
};

// The even and the odd floats of the 32 in a then b.
DT_AVX512 void deinterleave16(__m512 a, __m512 b, __m512& even, __m512& odd) {
  const __m512i ev = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
  even = _mm512_permutex2var_ps(a, ev, b);
  odd = _mm512_permutex2var_ps(a, _mm512_add_epi32(ev, _mm512_set1_epi32(1)), b);
}

// Sixteen points' (u, v) from interleaved uv (cnt < 16: the first cnt); the live lanes (finite, below cnt)
// as live_lanes: the others read (0.5, 0.5) and write nothing.
DT_AVX512 __mmask16 load16(const float* uv, int cnt, __m512& u, __m512& v) {
  const __mmask16 lo = static_cast<__mmask16>(cnt >= 8 ? 0xFFFF : (1u << (2 * cnt)) - 1);
  const __mmask16 hi = static_cast<__mmask16>(cnt >= 16 ? 0xFFFF : cnt <= 8 ? 0 : (1u << (2 * (cnt - 8))) - 1);
  const __m512 a = _mm512_maskz_loadu_ps(lo, uv), b = _mm512_maskz_loadu_ps(hi, uv + 16);
  deinterleave16(a, b, u, v);
  const __m512 z = _mm512_add_ps(_mm512_sub_ps(u, u), _mm512_sub_ps(v, v));
  const __mmask16 live = _mm512_cmp_ps_mask(z, _mm512_setzero_ps(), _CMP_EQ_OQ) &
                         static_cast<__mmask16>(cnt >= 16 ? 0xFFFF : (1u << cnt) - 1);
  u = _mm512_mask_blend_ps(live, _mm512_set1_ps(0.5f), u);
  v = _mm512_mask_blend_ps(live, _mm512_set1_ps(0.5f), v);
  return live;
}

// Whether a group's rows can be read as runs of 64-bit pairs of floats: where a row's K taps lie within K
// adjacent texels in every lane (all but where a repeat wrap's seam splits them), a planar channel's K
// texels are K / 2 gathers of eight pairs a half-group (read_run16), and C = 3 or 4 interleaved channels'
// C x K floats C x K / 2 such gathers, instead of K gathers of sixteen floats a channel: half the loads,
// the same texels and arithmetic. Measured (1024^2 RGB texture, 512^2 points of a rotated view, 2 threads,
// in a loop, in one process with and without): bilinear 0.88-0.91x the time planar, 0.91-0.95x
// channels_last; bicubic 0.81-0.86x and 0.77-0.82x.
template <int K>
DT_AVX512 void pair_taps16(const Args<float>& A, Group16<K>& g) {
  g.paired = false;
  const bool planar = A.xs == 1, interleaved = A.cs == 1 && A.xs == A.C && (A.C == 3 || A.C == 4);
  if (!(planar || interleaved) || A.W < K || A.wrap_u == BORDER || A.wrap_v == BORDER) return;  // border: masked
  const __m512i p = _mm512_min_epi32(g.ax.i[0], _mm512_set1_epi32(static_cast<int32_t>(A.W - K)));
  __m512i s[K];
  __mmask16 near = 0xFFFF, in_order = 0xFFFF;
  for (int q = 0; q < K; ++q) {
    s[q] = _mm512_sub_epi32(g.ax.i[q], p);
    near &= _mm512_cmplt_epu32_mask(s[q], _mm512_set1_epi32(K));
    in_order &= _mm512_cmpeq_epi32_mask(s[q], _mm512_set1_epi32(q));
  }
  if (near != 0xFFFF) return;
  g.paired = true;
  g.interior = in_order == 0xFFFF;
  g.cols[0] = planar ? p : _mm512_mullo_epi32(p, _mm512_set1_epi32(static_cast<int32_t>(A.xs)));
  for (int q = 0; q < K; ++q) {
    g.odd[q] = _mm512_test_epi32_mask(s[q], _mm512_set1_epi32(1));
    g.upper[q] = _mm512_test_epi32_mask(s[q], _mm512_set1_epi32(2));
  }
}

// v[f]: float f of each lane's run of N floats (N even) from chan + at, read as N / 2 64-bit gathers a
// half-group.
template <int N>
DT_AVX512 void read_run16(const float* chan, __m512i at, __m512 (&v)[N]) {
  for (int h = 0; h < N / 2; ++h) {
    const __m512i idx = _mm512_add_epi32(at, _mm512_set1_epi32(2 * h));
    const __m512 lo = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_castsi512_si256(idx), chan, 4));
    const __m512 hi = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_extracti64x4_epi64(idx, 1), chan, 4));
    deinterleave16(lo, hi, v[2 * h], v[2 * h + 1]);
  }
}

// Tap q of a paired group from its row's run v, whose texel k starts at float k * stride.
template <int K>
DT_AVX512 __m512 run_tap16(const Group16<K>& g, const __m512* v, int q, int stride) {
  if (g.interior) return v[q * stride];
  const __m512 low = _mm512_mask_blend_ps(g.odd[q], v[0], v[stride]);
  if constexpr (K == 2) return low;
  return _mm512_mask_blend_ps(g.upper[q], low, _mm512_mask_blend_ps(g.odd[q], v[2 * stride], v[3 * stride]));
}

// Whether the sixteen-point forward writes its output's whole lines with non-temporal stores: where the
// output [B, C, *S] is kStreamBytes or more. A store that misses fetches its line first (a read for
// ownership) and holds one of the core's few line-fill buffers for the whole trip, buffers that the texel
// reads of scattered points are waiting on (measured: a 1024^2 RGB channels_last forward of 512^2 uniformly
// random points reads 2.6 lines a point and waits on them, Dr.Jit's as much); a group's sixteen values of a
// channel are one whole line, which a non-temporal store writes without reading it. Measured on a busy
// 2-core VM (1 thread, CPU time, 1024^2 RGB texture, 512^2 points, bilinear, in one process with and
// without, blocks of 8 calls, 4 runs): channels_last 0.90-0.99x the time with uniformly random uv and
// 0.76-0.85x with a rotated view, planar 0.95-1.02x and 0.60-0.87x; with the output summed after each
// call (its reader pays for the lines not cached) 0.94x and 0.85x channels_last. An output that large
// leaves L2 before it is read anyway; a smaller one is left in the caches for its reader.
constexpr int64_t kStreamBytes = int64_t(1) << 20;

std::atomic<bool>& stream_switch() {
  static std::atomic<bool> on{true};
  return on;
}

// Stores sixteen values of one channel: a non-finite coordinate reads NaN; lanes past cnt are not written.
// stream: a whole aligned line goes out non-temporally (kStreamBytes).
template <int K>
DT_AVX512 void store16(const Group16<K>& g, __m512 sum, float* o, bool stream) {
  if (g.live == 0xFFFF) {
    if (stream && (reinterpret_cast<uintptr_t>(o) & 63) == 0) return _mm512_stream_ps(o, sum);
    return _mm512_storeu_ps(o, sum);
  }
  const __m512 out = _mm512_mask_blend_ps(g.live, _mm512_set1_ps(std::numeric_limits<float>::quiet_NaN()), sum);
  _mm512_mask_storeu_ps(o, static_cast<__mmask16>(g.cnt >= 16 ? 0xFFFF : (1u << g.cnt) - 1), out);
}

template <int K>
DT_AVX512 void prepare16(const Args<float>& A, __m512 u, __m512 v, Group16<K>& g) {
  axis16<K>(u, static_cast<int32_t>(A.W), A.wrap_u, g.ax);
  axis16<K>(v, static_cast<int32_t>(A.H), A.wrap_v, g.ay);
  const __m512i rs = _mm512_set1_epi32(static_cast<int32_t>(A.rs)), xs = _mm512_set1_epi32(static_cast<int32_t>(A.xs));
  for (int r = 0; r < K; ++r) {
    g.rows[r] = _mm512_mullo_epi32(g.ay.i[r], rs);
    g.cols[r] = A.xs == 1 ? g.ax.i[r] : _mm512_mullo_epi32(g.ax.i[r], xs);
  }
  pair_taps16<K>(A, g);
}

template <int K>
DT_AVX512 void prefetch16(const Group16<K>& g, const float* base, const Args<float>& A) {
  alignas(64) int32_t o[K][16];
  for (int r = 0; r < K; ++r) _mm512_store_si512(o[r], _mm512_add_epi32(g.rows[r], g.cols[0]));
  prefetch_rows<K, 16, false>(o, base, A);
}

template <int K, int CC, bool kBorder>
DT_AVX512 void forward16(const Args<float>& A, const Group16<K>& g, float* o, int64_t M, bool stream) {
  const int64_t C = CC > 0 ? CC : A.C;
  const float* tex = g.tex;
  if constexpr (CC > 1 && !kBorder) {
    if (g.paired && A.xs != 1) {  // interleaved: one run of C x K floats a row
      __m512 sum[CC];
      for (int c = 0; c < CC; ++c) sum[c] = _mm512_setzero_ps();
      for (int r = 0; r < K; ++r) {
        __m512 v[CC * K];
        read_run16(tex, _mm512_add_epi32(g.rows[r], g.cols[0]), v);
        for (int c = 0; c < CC; ++c) {
          __m512 acc = _mm512_setzero_ps();
          for (int q = 0; q < K; ++q) acc = _mm512_add_ps(acc, _mm512_mul_ps(g.ax.w[q], run_tap16(g, v + c, q, CC)));
          sum[c] = _mm512_add_ps(sum[c], _mm512_mul_ps(g.ay.w[r], acc));
        }
      }
      for (int c = 0; c < CC; ++c) store16(g, sum[c], o + c * M, stream);
      return;
    }
  }
  const __m512 border = _mm512_set1_ps(A.border);
  for (int64_t c = 0; c < C; ++c) {
    const float* chan = tex + c * A.cs;
    __m512 sum = _mm512_setzero_ps();
    for (int r = 0; r < K; ++r) {
      __m512 acc = _mm512_setzero_ps();
      if (!kBorder && g.paired) {
        __m512 v[K];
        read_run16(chan, _mm512_add_epi32(g.rows[r], g.cols[0]), v);
        for (int q = 0; q < K; ++q) acc = _mm512_add_ps(acc, _mm512_mul_ps(g.ax.w[q], run_tap16(g, v, q, 1)));
      } else {
        for (int q = 0; q < K; ++q) {
          const __m512i idx = _mm512_add_epi32(g.rows[r], g.cols[q]);
          const __m512 val = kBorder ? _mm512_mask_i32gather_ps(border, g.ay.in[r] & g.ax.in[q], idx, chan, 4)
                                     : _mm512_i32gather_ps(idx, chan, 4);
          acc = _mm512_add_ps(acc, _mm512_mul_ps(g.ax.w[q], val));
        }
      }
      sum = _mm512_add_ps(sum, _mm512_mul_ps(g.ay.w[r], acc));
    }
    store16(g, sum, o + c * M, stream);
  }
}

constexpr int kGroups16 = kBlock / 16;

// prepare_block with groups of sixteen.
template <int K>
DT_AVX512 int prepare_block16(const Args<float>& A, int64_t C, Walk& w, Group16<K>* grp) {
  int n = 0;
  for (int64_t first; n < kGroups16 && w.next(16, first, grp[n].cnt); ++n) {
    Group16<K>& g = grp[n];
    __m512 u, v;
    g.tex = group_start(A, w, first, C, 2, g.at);
    g.live = load16(A.uv + 2 * first, g.cnt, u, v);
    prepare16<K>(A, u, v, g);
    if (forward_prefetch<K>(A)) prefetch16<K>(g, g.tex, A);
  }
  return n;
}

// forward_range_avx2 sixteen points at a time.
template <int KIND, int CC, bool kBorder>
__attribute__((target("avx512f,avx512dq,avx2,fma"))) void forward_range_avx512(int64_t lo, int64_t hi,
                                                                                const Args<float>& A,
                                                                                const Tiles& t, float* out,
                                                                                bool stream) {
  constexpr int K = taps_of<KIND>();
  const int64_t C = CC > 0 ? CC : A.C;
  Walk w{t, lo, hi};
  in_two_blocks<Group16<K>, kGroups16>(
      [&](Group16<K>* b) __attribute__((target("avx512f,avx512dq,avx2,fma"))) {
        return prepare_block16<K>(A, C, w, b);
      },
      [&](const Group16<K>& g) __attribute__((target("avx512f,avx512dq,avx2,fma"))) {
        forward16<K, CC, kBorder>(A, g, out + g.at, A.M, stream);
      });
  if (stream) _mm_sfence();  // the non-temporal stores visible before the call returns
}

// out[K * j + q] = s[q][j] (K = 2 or 4): eight points' K shares of a row of taps, each point's side by side.
template <int K>
DT_AVX2 void runs8(const __m256* s, float* out) {
  const __m256 t0 = _mm256_unpacklo_ps(s[0], s[1]), t1 = _mm256_unpackhi_ps(s[0], s[1]);  // points 0 1 4 5, 2 3 6 7
  if constexpr (K == 2) {
    _mm256_storeu_ps(out, _mm256_permute2f128_ps(t0, t1, 0x20));
    _mm256_storeu_ps(out + 8, _mm256_permute2f128_ps(t0, t1, 0x31));
  } else {
    const __m256 t2 = _mm256_unpacklo_ps(s[2], s[3]), t3 = _mm256_unpackhi_ps(s[2], s[3]);
    const __m256 u[4] = {_mm256_shuffle_ps(t0, t2, 0x44), _mm256_shuffle_ps(t0, t2, 0xEE),
                         _mm256_shuffle_ps(t1, t3, 0x44), _mm256_shuffle_ps(t1, t3, 0xEE)};  // points k and k + 4
    for (int k = 0; k < 4; ++k) {
      _mm_storeu_ps(out + 4 * k, _mm256_castps256_ps128(u[k]));
      _mm_storeu_ps(out + 16 + 4 * k, _mm256_extractf128_ps(u[k], 1));
    }
  }
}

// at[0, K) += s[0, K) float by float (K = 2 or 4).
template <int K>
DT_AVX2 void add_run(float* at, const float* s) {
  if constexpr (K == 2) {
    const __m128 t = _mm_loadl_pi(_mm_setzero_ps(), reinterpret_cast<const __m64*>(at));
    _mm_storel_pi(reinterpret_cast<__m64*>(at),
                  _mm_add_ps(t, _mm_loadl_pi(_mm_setzero_ps(), reinterpret_cast<const __m64*>(s))));
  } else {
    _mm_storeu_ps(at, _mm_add_ps(_mm_loadu_ps(at), _mm_loadu_ps(s)));
  }
}

// Of the lanes `adjacent` (eight points, in scatter order, whose K taps along a row are the K texels from
// column x[j] on), those whose texture-gradient adds go a row at a time (add_run): not where a point's run
// partly overlaps the run of one of the two points before it, nor where it meets exactly one added float by
// float. There a K-float load would straddle earlier stores not yet written, which cannot forward to it and
// stall it (measured, without this: a backward with points 0.65 texels apart 1.09-1.16x slower than float by
// float). The same sums either way: each point adds once to each texel of a run, in the points' order.
template <int K>
DT_AVX2 int run_lanes8(__m256i x, int adjacent) {
  const __m256i z = _mm256_setzero_si256(), k = _mm256_set1_epi32(K);
  int part = 0, eq[3] = {0, 0, 0};
  for (int back = 1; back <= 2; ++back) {
    const __m256i before = _mm256_permutevar8x32_epi32(
        x, back == 1 ? _mm256_setr_epi32(0, 0, 1, 2, 3, 4, 5, 6) : _mm256_setr_epi32(0, 1, 0, 1, 2, 3, 4, 5));
    const __m256i d = _mm256_abs_epi32(_mm256_sub_epi32(x, before));
    const int lanes = 0xFF << back & 0xFF;
    const __m256i same = _mm256_cmpeq_epi32(d, z);
    part |= _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_andnot_si256(same, _mm256_cmpgt_epi32(k, d)))) & lanes;
    eq[back] = _mm256_movemask_ps(_mm256_castsi256_ps(same)) & lanes;
  }
  int vec = 0;
  for (int j = 0, ok = adjacent & ~part; j < 8; ++j) {
    const bool meets_float_adds = (eq[1] >> j & 1 && !(vec >> (j - 1) & 1)) || (eq[2] >> j & 1 && !(vec >> (j - 2) & 1));
    vec |= (ok >> j & 1 && !meets_float_adds) << j;
  }
  return vec;
}

// The lanes whose K taps along a row are K adjacent texels in order (planar columns): all but a repeat seam,
// a clamped edge and mirrored taps.
template <int K>
DT_AVX2 int adjacent8(const Group8<K>& g) {
  __m256i same = _mm256_set1_epi32(-1);
  for (int q = 1; q < K; ++q)
    same = _mm256_and_si256(same, _mm256_cmpeq_epi32(g.cols[q], _mm256_add_epi32(g.cols[0], _mm256_set1_epi32(q))));
  return _mm256_movemask_ps(_mm256_castsi256_ps(same));
}

// The backward of a group of points p[0..g.cnt) (any indices into [B * M]; the group's rows include each
// point's texture offset): uv gradients into guv (not null), texture gradients scattered into gt (not null),
// for the live lanes only. The taps, the uv gradient and each tap's share of the output gradient come eight
// points at a time; the scatter adds the shares one point after another in the scalar loop's order (the sums
// equal at any thread count, bands.h), a row's K shares as one add of K floats where the taps are adjacent
// texels of a planar texture (run_lanes8). Measured (1024^2 RGB texture, 512^2 points of a rotated view,
// 2 threads, in a loop, in one process with and without the runs): forward+backward 0.91-0.95x the time
// for bilinear and 0.93x for bicubic with points 2.6 texels apart, 0.97-1.01x and 0.98-1.00x at 1.3 and 0.65.
template <int K, int CC, bool kBorder>
DT_AVX2 void backward8(const Args<float>& A, const Group8<K>& g, const int64_t* p, __m256i gofs, const float* grad,
                       float* gt, float* guv) {
  const int64_t C = CC > 0 ? CC : A.C, M = A.M;
  if (guv != nullptr) {
    const __m256 border = _mm256_set1_ps(A.border);
    __m256 sx = _mm256_setzero_ps(), sy = _mm256_setzero_ps();
    for (int64_t c = 0; c < C; ++c) {
      const float* chan = A.tex + c * A.cs;
      __m256 cx = _mm256_setzero_ps(), cy = _mm256_setzero_ps();
      for (int r = 0; r < K; ++r) {
        __m256 rx = _mm256_setzero_ps(), rv = _mm256_setzero_ps();
        for (int q = 0; q < K; ++q) {
          const __m256 val = texels8<kBorder>(chan, g, r, q, border);
          rx = _mm256_add_ps(rx, _mm256_mul_ps(g.ax.dw[q], val));
          rv = _mm256_add_ps(rv, _mm256_mul_ps(g.ax.w[q], val));
        }
        cx = _mm256_add_ps(cx, _mm256_mul_ps(g.ay.w[r], rx));
        cy = _mm256_add_ps(cy, _mm256_mul_ps(g.ay.dw[r], rv));
      }
      const __m256 gc = _mm256_i32gather_ps(grad + c * M, gofs, 4);
      sx = _mm256_add_ps(sx, _mm256_mul_ps(gc, cx));
      sy = _mm256_add_ps(sy, _mm256_mul_ps(gc, cy));
    }
    alignas(32) float gx[8], gy[8];
    _mm256_store_ps(gx, _mm256_mul_ps(sx, _mm256_set1_ps(static_cast<float>(A.W))));
    _mm256_store_ps(gy, _mm256_mul_ps(sy, _mm256_set1_ps(static_cast<float>(A.H))));
    for (int j = 0; j < g.cnt; ++j)
      if (g.live >> j & 1) guv[2 * p[j]] = gx[j], guv[2 * p[j] + 1] = gy[j];
  }
  if (gt == nullptr) return;
  alignas(32) int32_t idx[K][K][8], in[K][K][8];
  for (int r = 0; r < K; ++r)
    for (int q = 0; q < K; ++q) {
      _mm256_store_si256(reinterpret_cast<__m256i*>(idx[r][q]), _mm256_add_epi32(g.rows[r], g.cols[q]));
      if (kBorder) _mm256_store_si256(reinterpret_cast<__m256i*>(in[r][q]), _mm256_and_si256(g.ay.in[r], g.ax.in[q]));
    }
  const int runs = !kBorder && A.xs == 1 ? run_lanes8<K>(g.cols[0], adjacent8(g)) : 0;
  alignas(32) float run[K][8 * K];  // run[r][K * j + q]: point j's share of tap (r, q)
  for (int64_t c = 0; c < C; ++c) {
    const __m256 gc = _mm256_i32gather_ps(grad + c * M, gofs, 4);
    for (int r = 0; r < K; ++r) {
      const __m256 gr = _mm256_mul_ps(gc, g.ay.w[r]);
      __m256 sq[K];
      for (int q = 0; q < K; ++q) sq[q] = _mm256_mul_ps(gr, g.ax.w[q]);
      runs8<K>(sq, run[r]);
    }
    float* tc = gt + c * A.cs;
    for (int j = 0; j < g.cnt; ++j) {
      if (!(g.live >> j & 1)) continue;
      for (int r = 0; r < K; ++r) {
        const float* sj = run[r] + K * j;
        if (runs >> j & 1) {
          add_run<K>(tc + idx[r][0][j], sj);
          continue;
        }
        for (int q = 0; q < K; ++q)
          if (!kBorder || in[r][q][j]) tc[idx[r][q][j]] += sj[q];
      }
    }
  }
}

// A group of points for backward8: its taps (whose rows include the points' texture offsets, b * image) and
// the points' offsets in grad [B, C, M].
template <int K>
struct PointGroup8 {
  Group8<K> g;
  __m256i gofs;
};

// Prepares the next block of groups of points idx[s, n) for backward8 and prefetches the lines it reads
// (grad; the texture, for guv) and writes (gt). Returns the group count (0 where s >= n).
template <int K, int CC>
DT_AVX2 int prepare_points(const Args<float>& A, const int64_t* idx, int64_t s, int64_t n, const float* grad,
                           const float* gt, const float* guv, PointGroup8<K>* pg) {
  const int64_t C = CC > 0 ? CC : A.C, M = A.M;
  const int m = static_cast<int>(std::min<int64_t>(kGroups, (n - s + 7) / 8));
  for (int i = 0; i < m; ++i) {
    Group8<K>& g = pg[i].g;
    const int64_t first = s + 8 * i;
    const int cnt = static_cast<int>(std::min<int64_t>(8, n - first));
    alignas(32) float us[8], vs[8];
    alignas(32) int32_t go[8], to[8];
    for (int j = 0; j < 8; ++j) {
      const int64_t p = idx[first + std::min(j, cnt - 1)], b = p / M;  // a tail repeats its last point
      us[j] = A.uv[2 * p];
      vs[j] = A.uv[2 * p + 1];
      go[j] = static_cast<int32_t>(p + b * (C - 1) * M);
      to[j] = static_cast<int32_t>((A.Bt == 1 ? 0 : b) * A.image);
    }
    __m256 u = _mm256_load_ps(us), v = _mm256_load_ps(vs);
    g.cnt = cnt;
    g.live = live_lanes(cnt, u, v);
    pg[i].gofs = _mm256_load_si256(reinterpret_cast<const __m256i*>(go));
    // A band's points come in runs along the pixel rows, so a group's output gradients mostly share a line
    // a channel. Measured with and without (1024^2 RGB texture, 512^2 points of a rotated view, 2 threads):
    // 0.95-0.97x the bicubic backward's time, the bilinear one's unchanged (0.98-1.00x).
    for (int64_t c = 0; c < C; ++c) {
      DT_PREFETCH(grad + c * M + go[0], false);
      if ((go[0] ^ go[cnt - 1]) >> 4) DT_PREFETCH(grad + c * M + go[cnt - 1], false);
    }
    prepare8<K>(A, u, v, g);
    const __m256i tb = _mm256_load_si256(reinterpret_cast<const __m256i*>(to));
    for (int r = 0; r < K; ++r) g.rows[r] = _mm256_add_epi32(g.rows[r], tb);
    if (guv != nullptr) prefetch8<K, false>(g, A.tex, A);
    if (gt != nullptr) prefetch8<K, true>(g, gt, A);
  }
  return m;
}

// The backward of points idx[0, n) by blocks of groups of eight (see backward8; the last group partial).
template <int KIND, int CC, bool kBorder>
__attribute__((target("avx2,fma"))) void backward_avx2(const Args<float>& A, const int64_t* idx, int64_t n,
                                                       const float* grad, float* gt, float* guv) {
  constexpr int K = taps_of<KIND>();
  int64_t next = 0, s = 0;
  in_two_blocks<PointGroup8<K>, kGroups>(
      [&](PointGroup8<K>* b) __attribute__((target("avx2,fma"))) {
        const int m = prepare_points<K, CC>(A, idx, next, n, grad, gt, guv, b);
        next += 8 * m;
        return m;
      },
      [&](const PointGroup8<K>& b) __attribute__((target("avx2,fma"))) {
        backward8<K, CC, kBorder>(A, b.g, idx + s, b.gofs, grad, gt, guv);
        s += 8;
      });
}

// The band keys of points [lo, hi) for the banded scatter of backward_avx2, eight at a time: keys[p] =
// b * nb + band[r] for the first row r that point p writes (first_row of the taps axis8 gives, which are the
// rows backward8 writes: keys from the scalar loop's double arithmetic could name a row one off), -1 for a
// point that writes nothing (a non-finite coordinate, or every tap on the border constant: those go to
// border, where it is not null, for their uv gradient). band: each row's band.
template <int KIND>
__attribute__((target("avx2,fma"))) void keys_avx2(const Args<float>& A, int64_t lo, int64_t hi, int64_t nb,
                                                  const int32_t* band, int32_t* keys, std::vector<int64_t>* border) {
  constexpr int K = taps_of<KIND>();
  const __m256i none = _mm256_set1_epi32(-1), big = _mm256_set1_epi32(std::numeric_limits<int32_t>::max());
  Axis8<K> ay;
  alignas(32) int32_t key[8], row[8];
  for (int64_t s = lo; s < hi; s += 8) {
    const int cnt = static_cast<int>(std::min<int64_t>(8, hi - s));
    __m256 u, v;
    const int live = load8(A.uv + 2 * s, cnt, u, v);
    axis8<K>(v, static_cast<int32_t>(A.H), A.wrap_v, ay);
    __m256i r = ay.i[0];
    if (A.wrap_v != REPEAT) {  // the least row read, -1 where every tap reads the border constant
      r = big;
      for (int q = 0; q < K; ++q) r = _mm256_min_epi32(r, _mm256_blendv_epi8(big, ay.i[q], ay.in[q]));
      r = _mm256_blendv_epi8(r, none, _mm256_cmpeq_epi32(r, big));
    }
    const int64_t b0 = A.Bt == 1 ? 0 : s / A.M, b1 = A.Bt == 1 ? 0 : (s + cnt - 1) / A.M;
    __m256i k = _mm256_i32gather_epi32(band, _mm256_max_epi32(r, _mm256_setzero_si256()), 4);
    k = _mm256_add_epi32(k, _mm256_set1_epi32(static_cast<int32_t>(b0 * nb)));
    _mm256_store_si256(reinterpret_cast<__m256i*>(key), k);
    _mm256_store_si256(reinterpret_cast<__m256i*>(row), r);
    for (int j = 0; j < cnt; ++j) {
      const bool writes = (live >> j & 1) && row[j] >= 0;
      if (b1 != b0 && writes) key[j] = static_cast<int32_t>((s + j) / A.M * nb + band[row[j]]);  // a batch edge
      keys[s + j] = writes ? key[j] : -1;
      if ((live >> j & 1) && row[j] < 0 && border != nullptr) border->push_back(s + j);
    }
  }
}

#endif

// Whether a float32 read of this kind and texture goes through the eight-point path.
// int32 texel offsets: the whole texture batch (the backward's groups mix textures through per-lane offsets).
bool simd_read(int64_t kind, const Tensor& texture) {
  return simd_on() && kind != NEAREST && texture.scalar_type() == kFloat32 &&
         texture.numel() < (int64_t(1) << 31);
}

// uv is [B, *S, 2] (the caller's pixel shape S, flattened nowhere): the points per batch entry, prod(S).
int64_t points_of(const Tensor& uv) {
  int64_t m = 1;
  for (int64_t d = 1; d + 1 < uv.dim(); ++d) m *= uv.size(d);
  return m;
}

// [B, C, *S] for uv [B, *S, 2]: the output's and the output gradient's shape.
std::vector<int64_t> out_shape(const Tensor& uv, int64_t C) {
  std::vector<int64_t> shape{uv.size(0), C};
  for (int64_t d = 1; d + 1 < uv.dim(); ++d) shape.push_back(uv.size(d));
  return shape;
}

template <typename scalar_t>
Args<scalar_t> args_of(const Tensor& texture, const Tensor& uv, const ReadOptions& opts) {
  Args<scalar_t> A;
  A.Bt = texture.size(0); A.C = texture.size(1); A.H = texture.size(2); A.W = texture.size(3);
  A.M = points_of(uv); A.image = A.C * A.H * A.W;
  A.cs = texture.stride(1); A.rs = texture.stride(2); A.xs = texture.stride(3);
  A.wrap_u = static_cast<int>(opts.wrap_u); A.wrap_v = static_cast<int>(opts.wrap_v);
  A.border = static_cast<scalar_t>(opts.border);
  A.tex = texture.mutable_data_ptr<scalar_t>();
  A.uv = uv.mutable_data_ptr<scalar_t>();
  return A;
}

void check_inputs(const Tensor& texture, const Tensor& uv, int64_t kind) {
  DT_CHECK(kind >= NEAREST && kind <= CUBIC, "sample: kind must be a filter code 0-2, got ", kind);
  DT_CHECK(texture.dim() == 4 && (texture.is_contiguous() || is_channels_last(texture)) &&
                  texture.is_cpu() && texture.size(1) >= 1 && texture.size(2) >= 1 && texture.size(3) >= 1,
              "sample: texture must be a contiguous or channels_last CPU tensor [Bt, C, H, W] with C, H, W >= 1");
  DT_CHECK(uv.dim() >= 2 && uv.size(-1) == 2 && uv.is_contiguous() && uv.scalar_type() == texture.scalar_type(),
              "sample: uv must be contiguous [B, *S, 2] of the texture's dtype");
  DT_CHECK(texture.size(0) == 1 || texture.size(0) == uv.size(0),
              "sample: the texture batch must be 1 or uv's batch");
  DT_CHECK(texture.size(2) < (1 << 30) && texture.size(3) < (1 << 30),
              "sample: texture sides must be under 2^30 texels (int32 indices)");
}

// Runs f(std::integral_constant<int, KIND>) for the filter code.
template <typename F>
void with_kind(int64_t kind, F&& f) {
  switch (kind) {
    case NEAREST: f(std::integral_constant<int, NEAREST>()); break;
    case LINEAR: f(std::integral_constant<int, LINEAR>()); break;
    default: f(std::integral_constant<int, CUBIC>());
  }
}

}  // namespace

Tensor sample(Tensor texture, Tensor uv, int64_t kind, const ReadOptions& opts) {
  check_inputs(texture, uv, kind);
  const int64_t B = uv.size(0), C = texture.size(1), M = points_of(uv);
  auto out = empty(out_shape(uv, C), options_of(uv));
  const bool simd = simd_read(kind, texture), wide = simd && wide_on();
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "sample_forward", [&] {
    const Args<scalar_t> A = args_of<scalar_t>(texture, uv, opts);
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    with_kind(kind, [&](auto k) {
      specialized(C, opts.wrap_u, opts.wrap_v, [&](auto cc, auto border_) {
        constexpr int KIND = decltype(k)::value, CC = decltype(cc)::value;
        constexpr bool kB = decltype(border_)::value;
#if DT_HAVE_AVX2
        if constexpr (std::is_same_v<scalar_t, float> && KIND != NEAREST) {
          if (simd) {
            const Tiles t(A, uv);
            const bool stream = stream_switch().load() && B * C * M * static_cast<int64_t>(sizeof(float)) >= kStreamBytes;
            parallel_for(0, t.count(B), 2048 / kTileCols, [&](int64_t lo, int64_t hi) {
              if (wide) return forward_range_avx512<KIND, CC, kB>(lo, hi, A, t, po, stream);
              forward_range_avx2<KIND, CC, kB>(lo, hi, A, t, po);
            });
            return;
          }
        }
#endif
        parallel_for(0, B * M, 2048,
                         [&](int64_t lo, int64_t hi) { forward_range<scalar_t, KIND, CC, kB>(lo, hi, A, po); });
      });
    });
  });
  return out;
}

std::tuple<Tensor, Tensor> sample_backward(Tensor texture, Tensor uv, Tensor grad,
                                                         int64_t kind, const ReadOptions& opts, bool need_texture,
                                                         bool need_uv) {
  check_inputs(texture, uv, kind);
  const int64_t B = uv.size(0), Bt = texture.size(0), C = texture.size(1), H = texture.size(2), M = points_of(uv);
  grad = contig(grad);
  DT_CHECK(grad.sizes() == IntArrayRef(out_shape(uv, C)) && grad.scalar_type() == uv.scalar_type(),
              "sample_backward: grad must be [B, C, *S] of uv's dtype for uv [B, *S, 2]");
  need_uv = need_uv && kind != NEAREST;
  // Laid out like the texture (planar or interleaved): the kernels index both with the same strides.
  Tensor gt = need_texture ? zeros_in_layout_of(texture)
                                  : Tensor();
  Tensor guv = need_uv ? zeros_like(uv) : Tensor();
  if (!need_texture && !need_uv) return {gt, guv};
  const bool simd = simd_read(kind, texture) && B * C * M < (int64_t(1) << 31);  // int32 gather offsets into grad
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "sample_backward", [&] {
    const Args<scalar_t> A = args_of<scalar_t>(texture, uv, opts);
    const scalar_t* pg = grad.mutable_data_ptr<scalar_t>();
    scalar_t* pgt = need_texture ? gt.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* pguv = need_uv ? guv.mutable_data_ptr<scalar_t>() : nullptr;
    with_kind(kind, [&](auto k) {
      constexpr int KIND = decltype(k)::value;
      specialized(C, opts.wrap_u, opts.wrap_v, [&](auto cc, auto border_) {
        constexpr int CC = decltype(cc)::value;
        constexpr bool kB = decltype(border_)::value;
        // The points of idx[0, n) in blocks: uv gradients, and texture gradients into tex (or none).
        auto blocks = [&](const int64_t* idx, int64_t n, scalar_t* tex) {
          Block<scalar_t, KIND> bl;
          int64_t s = 0;
#if DT_HAVE_AVX2
          if constexpr (std::is_same_v<scalar_t, float> && KIND != NEAREST) {
            if (simd) return backward_avx2<KIND, CC, kB>(A, idx, n, pg, tex, pguv);
          }
#endif
          for (; s < n; s += kBlock) {
            bl.cnt = static_cast<int>(std::min<int64_t>(kBlock, n - s));
            for (int j = 0; j < bl.cnt; ++j) bl.p[j] = idx[s + j];
            backward_block<scalar_t, KIND, CC, kB>(bl, A, pg, tex, pguv);
          }
        };
        if (!need_texture) {
          parallel_for(0, B * M, 2048, [&](int64_t lo, int64_t hi) {
            std::vector<int64_t> idx(hi - lo);
            for (int64_t p = lo; p < hi; ++p) idx[p - lo] = p;
            blocks(idx.data(), hi - lo, nullptr);
          });
          return;
        }
        // Bands of rows per texture: key = texture * nb + band, class = band parity.
        const int64_t nb = band_count(H, taps_of<KIND>());
        std::vector<int32_t> classes(Bt * nb);
        for (int64_t i = 0; i < Bt * nb; ++i) classes[i] = nb > 1 ? static_cast<int32_t>(i % nb % 2) : 0;
        std::vector<int32_t> keys(B * M), band(H);
        for (int64_t r = 0; r < H; ++r) band[r] = static_cast<int32_t>(band_of(r, H, nb));
        parallel_for(0, B * M, 4096, [&](int64_t lo, int64_t hi) {
          std::vector<int64_t> border_only;  // every tap on the border constant: the uv gradient alone
#if DT_HAVE_AVX2
          if constexpr (std::is_same_v<scalar_t, float> && KIND != NEAREST) {
            if (simd) {
              keys_avx2<KIND>(A, lo, hi, nb, band.data(), keys.data(), pguv != nullptr ? &border_only : nullptr);
              return blocks(border_only.data(), static_cast<int64_t>(border_only.size()), nullptr);
            }
          }
#endif
          Taps<taps_of<KIND>()> ty;
          double v[kBlock];
          for (int64_t s = lo; s < hi; s += kBlock) {
            const int cnt = static_cast<int>(std::min<int64_t>(kBlock, hi - s));
            for (int j = 0; j < cnt; ++j) v[j] = static_cast<double>(A.uv[2 * (s + j) + 1]);
            taps_block<KIND, scalar_t>(v, cnt, H, A.wrap_v, ty);
            for (int j = 0; j < cnt; ++j) {
              const int64_t p = s + j;
              if (!std::isfinite(A.uv[2 * p]) || !std::isfinite(v[j])) {
                keys[p] = -1;
                continue;
              }
              const int64_t r = first_row(ty, j, A.wrap_v);
              keys[p] = r < 0 ? -1 : static_cast<int32_t>((Bt == 1 ? 0 : p / M) * nb + band[r]);
              if (r < 0 && pguv != nullptr) border_only.push_back(p);
            }
          }
          blocks(border_only.data(), static_cast<int64_t>(border_only.size()), nullptr);
        });
        run_banded(keys.data(), B * M, classes, [&](const int64_t* idx, int64_t n) { blocks(idx, n, pgt); });
      });
    });
  });
  return {gt, guv};
}

bool set_simd(bool enabled) { return simd_switch().exchange(enabled); }

bool simd_available() { return DT_HAVE_AVX2 && cpu_has_avx2(); }

bool set_wide(bool enabled) { return wide_switch().exchange(enabled); }

bool wide_available() { return simd_available() && cpu_has_avx512(); }

bool set_stream(bool enabled) {
#if DT_HAVE_AVX2
  return stream_switch().exchange(enabled);
#else
  return enabled;
#endif
}

}  // namespace difftex
