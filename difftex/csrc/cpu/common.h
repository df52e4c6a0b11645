// The native CPU kernel of difftex's mip filters (difftex/texture/native):
// what its sources share. One translation unit per kernel (taps.cpp: the
// trilinear / nearest-mip / anisotropic / auto taps, forward and backward;
// front.cpp: their footprint front end; box.cpp: the pyramid's 2 x 2 box
// step; ewa.cpp: EWA, forward and backward), module.cpp binds them. Here:
// the constants each mirrored from one Python constant (module.cpp exports
// them, tests/texture/native/test_native.py checks they agree), the inline
// floor / wrap / fold helpers of a bilinear read, and the levels a point
// reads. The helpers stay in this header, inline, because the kernels call
// them in their innermost loops.
//
// The semantics are those of difftex's torch path (filters/trilinear.py
// mip_blend + filters/separable.py + wrap.py), which stays the tested
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
#pragma once

#include "stable.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

namespace difftex {

// 2^n for an integral n >= 0, exact, at compile time.
constexpr double exp2_exact(double n) {
  double r = 1.0;
  for (double i = 0; i < n; ++i) r *= 2.0;
  return r;
}

// The wrap modes by code: texture/wrap.py WRAP_CODES (the code is the
// mode's position in WRAP_MODES).
enum Wrap { REPEAT = 0, CLAMP = 1, MIRROR = 2, BORDER = 3 };

// 2^52: from here on a double has no fractional part (wrap.py INDEX_CAP).
constexpr double kTwo52 = exp2_exact(52);
// lod.py FAR: log2 of a zero / infinite length.
constexpr double kFar = 1.0e4;
// filters/anisotropic.py RATIO_TOL: a tap ratio within this of an integer rounds down.
constexpr double kRatioTol = 1e-4;
// filters/auto.py MAX_LOG2, and the ratio 2^MAX_LOG2 it caps.
constexpr double kMaxLog2 = 64.0;
constexpr double kMaxRatio = exp2_exact(kMaxLog2);
// filters/auto.py LOG2_FLOOR: log2 of auto's tap spacing floor (half a texel).
constexpr double kLog2Floor = -1.0;
// filters/ewa.py ALPHA (the Gaussian falloff) and MAX_MINOR (the minor axis
// cap on the coarsest level, in its texels).
constexpr double kAlpha = 2.0;
constexpr double kMaxMinor = 2.0;
// filters/gather.py _CUBIC_A: the Keys cubic's a (grid_sample's bicubic),
// and _FAR: past this distance in uv from [0, 1] every tap of every filter
// is off the texture (the single-level reads, single.cpp).
constexpr double kCubicA = -0.75;
constexpr double kFarUv = 8.0;

// The per-tap helpers below are small and called in the innermost loops;
// left to itself the compiler keeps some out of line (measured: 20% of the
// forward in calls that return their structs through memory).
#if defined(_MSC_VER)
#define DT_INLINE __forceinline
#else
#define DT_INLINE inline __attribute__((always_inline))
#endif

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
  r.k[0] = static_cast<int64_t>(k0);
  if (k0 < K - 1 && t > 0) {  // between two levels
    r.n = 2; r.wt[0] = 1.0 - t; r.dwt[0] = -1.0;
    r.k[1] = r.k[0] + 1; r.wt[1] = t; r.dwt[1] = 1.0;
  } else if (d_grad && k0 > 0) {
    // An integer level k0 > 0 where D needs a gradient: the derivative from below (DESIGN.md, "level
    // gradient"), so level k0 - 1 is read with weight 0 (trilinear.py mip_blend does the same).
    r.n = 2; r.wt[0] = 1.0; r.dwt[0] = 1.0;
    r.k[1] = r.k[0] - 1; r.wt[1] = 0.0; r.dwt[1] = -1.0;
  } else {  // an integer level alone (D = 0 included): no derivative
    r.n = 1; r.wt[0] = 1.0; r.dwt[0] = 0.0;
  }
  return r;
}

// The uniforms of stochastic filtering (filters/stochastic.py hashed_uniforms, which mirrors this in torch
// int64 arithmetic): SplitMix64's output at position counter + 1 of the stream seeded by seed, its top 53
// bits as a double in [0, 1). Counter-based: a point's draws depend on (seed, counter) alone, not on which
// thread reads it or in what order, so the result is the same bits at any thread count.
DT_INLINE uint64_t splitmix64(uint64_t z) {
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
  return z ^ (z >> 31);
}

DT_INLINE double draw_uniform(uint64_t seed, uint64_t counter) {
  return static_cast<double>(splitmix64(seed + (counter + 1) * 0x9E3779B97F4A7C15ULL) >> 11) *
         (1.0 / 9007199254740992.0);
}

// The first uniform of draw d of a point's k stratified draws (strata = k; one uniform a draw): draw_uniform
// moved into the stratum [j / k, (j + 1) / k) of j = d mod k, as hashed_uniforms does it in torch. The k
// draws of a point have consecutive counters, so each stratum holds one of them: their mean is still
// unbiased, with at most the variance of k independent draws.
DT_INLINE double stratified_uniform(uint64_t seed, int64_t d, int64_t strata) {
  return (static_cast<double>(d % strata) + draw_uniform(seed, static_cast<uint64_t>(d))) / static_cast<double>(strata);
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

// The levels' sizes, after checking levels [C, h, w], uv [M, 2], D [M],
// axis [M, 2] and count [M] (both empty for one tap a point); taps.cpp.
std::vector<Level> shapes(const std::vector<Tensor>& levels, const Tensor& uv, const Tensor& D,
                          const Tensor& axis, const Tensor& count);

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

// The eight-point AVX2 paths of the float32 reads (single.cpp, taps.cpp):
// whether this build has them (x86-64, GCC / Clang), whether this CPU runs
// them (AVX2 and FMA, checked once at run time) and the switch the tests
// turn (kernels.h set_simd).
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define DT_HAVE_AVX2 1
#define DT_AVX2 __attribute__((target("avx2,fma"), always_inline)) inline
inline bool cpu_has_avx2() {
  static const bool has = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return has;
}

// The vector paths' pipeline: groups of points in blocks of up to NB, two blocks in flight. Block i + 1 is
// prepared (fill(block) prepares its groups, which prefetches their lines, and returns how many; 0 at the
// end) before block i is read (read(group), group after group), so that the misses of a block overlap the
// reads of the one before (measured on single.cpp's forward: prefetching a block just before reading it
// left two threads no faster than one on a 1024^2 texture).
template <typename G, int NB, typename Fill, typename Read>
DT_AVX2 void in_two_blocks(Fill&& fill, Read&& read) {
  G blk[2][NB];
  for (int cur = 0, n = fill(blk[0]); n > 0; cur ^= 1) {
    const int m = fill(blk[cur ^ 1]);
    for (int i = 0; i < n; ++i) read(blk[cur][i]);
    n = m;
  }
}
#else
#define DT_HAVE_AVX2 0
inline bool cpu_has_avx2() { return false; }
#endif

// A prefetch of the line at addr (write: to be written), where the compiler has one: the kernels issue them
// ahead of their gathers and scatters so that the cache misses overlap.
#if defined(__GNUC__) || defined(__clang__)
#define DT_PREFETCH(addr, write) __builtin_prefetch((addr), (write) ? 1 : 0, 3)
#else
#define DT_PREFETCH(addr, write) ((void)(addr))
#endif

inline std::atomic<bool>& simd_switch() {
  static std::atomic<bool> on{true};
  return on;
}

inline bool simd_on() { return DT_HAVE_AVX2 && cpu_has_avx2() && simd_switch().load(); }

// The sixteen-point AVX-512 forward of single.cpp (AVX512F and AVX512DQ, checked once at run time), on
// where the CPU has it and simd_on(); set_wide turns it off, so that the tests run the eight-point path too.
#if DT_HAVE_AVX2
inline bool cpu_has_avx512() {
  static const bool has = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq");
  return has;
}
#else
inline bool cpu_has_avx512() { return false; }
#endif

inline std::atomic<bool>& wide_switch() {
  static std::atomic<bool> on{true};
  return on;
}

inline bool wide_on() { return simd_on() && cpu_has_avx512() && wide_switch().load(); }

}  // namespace difftex
