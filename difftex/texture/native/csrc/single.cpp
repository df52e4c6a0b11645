// The single-level reads on the CPU: nearest, bilinear and bicubic
// (filters/separable.py SeparableSample), forward and first-order
// backward, one pass over the points, threaded over them. The semantics
// are those of the gather reference (filters/gather.py), which the tests
// hold it to: texel coordinate x = u * n - 0.5, nearest rounds x half to
// even, bilinear reads floor(x) and floor(x) + 1, bicubic floor(x) - 1 ..
// floor(x) + 2 with the Keys kernel (a = kCubicA, grid_sample's), every
// index wrapped per axis as wrap.py does.
//
// Bilinear and bicubic fold u into one period first (common.h fold, as the
// mip taps do), in double: the same texels as the integer wrap. Nearest
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
    a.in[0] = wrap_int(index_of(static_cast<double>(std::nearbyint(x))), n, mode, &a.i[0]);
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

// The first row a point writes (its band's key): the wrapped first tap for
// repeat (its rows run on cyclically from there), else the least row read;
// -1 where every tap reads the border constant.
template <int K>
DT_INLINE int64_t first_row(const Line<K>& a, int mode) {
  if (mode == REPEAT) return a.i[0];
  int64_t r = -1;
  for (int q = 0; q < K; ++q)
    if (a.in[q] && (r < 0 || a.i[q] < r)) r = a.i[q];
  return r;
}

// The shapes and pointers of one call: texture [Bt, C, H, W], points
// p = b * M + e of uv [B, M, 2]; per-point arrays [B, C, M] (values,
// output gradients).
template <typename scalar_t>
struct Args {
  int64_t Bt, C, H, W, M, plane;
  int wrap_u, wrap_v;
  scalar_t border;
  const scalar_t* tex;
  const scalar_t* uv;
};

template <typename scalar_t, int KIND, int CC, bool kBorder>
void forward_range(int64_t lo, int64_t hi, const Args<scalar_t>& A, scalar_t* out) {
  constexpr int K = taps_of<KIND>();
  const int64_t C = CC > 0 ? CC : A.C, M = A.M;
  for (int64_t p = lo; p < hi; ++p) {
    const int64_t b = p / M, e = p - b * M;
    scalar_t* o = out + b * C * M + e;
    const scalar_t u = A.uv[2 * p], v = A.uv[2 * p + 1];
    if (!std::isfinite(u) || !std::isfinite(v)) {
      for (int64_t c = 0; c < C; ++c) o[c * M] = std::numeric_limits<scalar_t>::quiet_NaN();
      continue;
    }
    const auto ax = line<KIND>(u, A.W, A.wrap_u);
    const auto ay = line<KIND>(v, A.H, A.wrap_v);
    const scalar_t* t = A.tex + (A.Bt == 1 ? 0 : b) * C * A.plane;
    scalar_t wx[K], wy[K];
    for (int q = 0; q < K; ++q) wx[q] = static_cast<scalar_t>(ax.w[q]), wy[q] = static_cast<scalar_t>(ay.w[q]);
    for (int64_t c = 0; c < C; ++c) {
      const scalar_t* tc = t + c * A.plane;
      scalar_t s = 0;
      for (int r = 0; r < K; ++r) {
        const scalar_t* row = tc + ay.i[r] * A.W;
        scalar_t acc = 0;
        for (int q = 0; q < K; ++q) acc += wx[q] * (!kBorder || (ay.in[r] && ax.in[q]) ? row[ax.i[q]] : A.border);
        s += wy[r] * acc;
      }
      o[c * M] = s;
    }
  }
}

// Point p's backward: its uv gradient (need_uv) and its texture gradient
// scattered into gt (gt not null).
template <typename scalar_t, int KIND, int CC, bool kBorder>
DT_INLINE void backward_point(int64_t p, const Args<scalar_t>& A, const scalar_t* grad, scalar_t* gt,
                              scalar_t* guv) {
  constexpr int K = taps_of<KIND>();
  const int64_t C = CC > 0 ? CC : A.C, M = A.M;
  const scalar_t u = A.uv[2 * p], v = A.uv[2 * p + 1];
  if (!std::isfinite(u) || !std::isfinite(v)) return;
  const int64_t b = p / M, e = p - b * M;
  const scalar_t* g = grad + b * C * M + e;
  const auto ax = line<KIND>(u, A.W, A.wrap_u);
  const auto ay = line<KIND>(v, A.H, A.wrap_v);
  scalar_t wx[K], wy[K];
  for (int q = 0; q < K; ++q) wx[q] = static_cast<scalar_t>(ax.w[q]), wy[q] = static_cast<scalar_t>(ay.w[q]);
  if (KIND != NEAREST && guv != nullptr) {
    const scalar_t* t = A.tex + (A.Bt == 1 ? 0 : b) * C * A.plane;
    scalar_t dx[K], dy[K];
    for (int q = 0; q < K; ++q) dx[q] = static_cast<scalar_t>(ax.dw[q]), dy[q] = static_cast<scalar_t>(ay.dw[q]);
    scalar_t sx = 0, sy = 0;
    for (int64_t c = 0; c < C; ++c) {
      const scalar_t* tc = t + c * A.plane;
      scalar_t cx = 0, cy = 0;
      for (int r = 0; r < K; ++r) {
        const scalar_t* row = tc + ay.i[r] * A.W;
        scalar_t rx = 0, rv = 0;
        for (int q = 0; q < K; ++q) {
          const scalar_t val = !kBorder || (ay.in[r] && ax.in[q]) ? row[ax.i[q]] : A.border;
          rx += dx[q] * val;
          rv += wx[q] * val;
        }
        cx += wy[r] * rx;
        cy += dy[r] * rv;
      }
      sx += g[c * M] * cx;
      sy += g[c * M] * cy;
    }
    guv[2 * p] = static_cast<scalar_t>(sx * ax.slope * static_cast<double>(A.W));
    guv[2 * p + 1] = static_cast<scalar_t>(sy * ay.slope * static_cast<double>(A.H));
  }
  if (gt != nullptr) {
    scalar_t* tg = gt + (A.Bt == 1 ? 0 : b) * C * A.plane;
    for (int64_t c = 0; c < C; ++c) {
      const scalar_t gc = g[c * M];
      scalar_t* tc = tg + c * A.plane;
      for (int r = 0; r < K; ++r) {
        if (kBorder && !ay.in[r]) continue;
        scalar_t* row = tc + ay.i[r] * A.W;
        const scalar_t gr = gc * wy[r];
        for (int q = 0; q < K; ++q)
          if (!kBorder || ax.in[q]) row[ax.i[q]] += gr * wx[q];
      }
    }
  }
}

template <typename scalar_t>
Args<scalar_t> args_of(const torch::Tensor& texture, const torch::Tensor& uv, const ReadOptions& opts) {
  Args<scalar_t> A;
  A.Bt = texture.size(0); A.C = texture.size(1); A.H = texture.size(2); A.W = texture.size(3);
  A.M = uv.size(1); A.plane = A.H * A.W;
  A.wrap_u = static_cast<int>(opts.wrap_u); A.wrap_v = static_cast<int>(opts.wrap_v);
  A.border = static_cast<scalar_t>(opts.border);
  A.tex = texture.data_ptr<scalar_t>();
  A.uv = uv.data_ptr<scalar_t>();
  return A;
}

void check_inputs(const torch::Tensor& texture, const torch::Tensor& uv, int64_t kind) {
  TORCH_CHECK(kind >= NEAREST && kind <= CUBIC, "sample: kind must be a filter code 0-2, got ", kind);
  TORCH_CHECK(texture.dim() == 4 && texture.is_contiguous() && texture.device().is_cpu() &&
                  texture.size(1) >= 1 && texture.size(2) >= 1 && texture.size(3) >= 1,
              "sample: texture must be a contiguous CPU tensor [Bt, C, H, W] with C, H, W >= 1");
  TORCH_CHECK(uv.dim() == 3 && uv.size(2) == 2 && uv.is_contiguous() && uv.scalar_type() == texture.scalar_type(),
              "sample: uv must be contiguous [B, M, 2] of the texture's dtype");
  TORCH_CHECK(texture.size(0) == 1 || texture.size(0) == uv.size(0),
              "sample: the texture batch must be 1 or uv's batch");
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

torch::Tensor sample(torch::Tensor texture, torch::Tensor uv, int64_t kind, const ReadOptions& opts) {
  check_inputs(texture, uv, kind);
  const int64_t B = uv.size(0), C = texture.size(1), M = uv.size(1);
  auto out = torch::empty({B, C, M}, uv.options());
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "sample_forward", [&] {
    const Args<scalar_t> A = args_of<scalar_t>(texture, uv, opts);
    scalar_t* po = out.data_ptr<scalar_t>();
    with_kind(kind, [&](auto k) {
      specialized(C, opts.wrap_u, opts.wrap_v, [&](auto cc, auto border_) {
        at::parallel_for(0, B * M, 2048, [&](int64_t lo, int64_t hi) {
          forward_range<scalar_t, decltype(k)::value, decltype(cc)::value, decltype(border_)::value>(lo, hi, A, po);
        });
      });
    });
  });
  return out;
}

std::tuple<torch::Tensor, torch::Tensor> sample_backward(torch::Tensor texture, torch::Tensor uv, torch::Tensor grad,
                                                         int64_t kind, const ReadOptions& opts, bool need_texture,
                                                         bool need_uv) {
  check_inputs(texture, uv, kind);
  const int64_t B = uv.size(0), Bt = texture.size(0), C = texture.size(1), H = texture.size(2), M = uv.size(1);
  grad = grad.contiguous();
  TORCH_CHECK(grad.dim() == 3 && grad.size(0) == B && grad.size(1) == C && grad.size(2) == M &&
                  grad.scalar_type() == uv.scalar_type(), "sample_backward: grad must be [B, C, M] of uv's dtype");
  need_uv = need_uv && kind != NEAREST;
  torch::Tensor gt = need_texture ? torch::zeros_like(texture) : torch::Tensor();
  torch::Tensor guv = need_uv ? torch::zeros_like(uv) : torch::Tensor();
  if (!need_texture && !need_uv) return {gt, guv};
  AT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "sample_backward", [&] {
    const Args<scalar_t> A = args_of<scalar_t>(texture, uv, opts);
    const scalar_t* pg = grad.data_ptr<scalar_t>();
    scalar_t* pgt = need_texture ? gt.data_ptr<scalar_t>() : nullptr;
    scalar_t* pguv = need_uv ? guv.data_ptr<scalar_t>() : nullptr;
    with_kind(kind, [&](auto k) {
      constexpr int KIND = decltype(k)::value;
      specialized(C, opts.wrap_u, opts.wrap_v, [&](auto cc, auto border_) {
        constexpr int CC = decltype(cc)::value;
        constexpr bool kB = decltype(border_)::value;
        auto one = [&](int64_t p) { backward_point<scalar_t, KIND, CC, kB>(p, A, pg, pgt, pguv); };
        if (!need_texture) {
          at::parallel_for(0, B * M, 2048, [&](int64_t lo, int64_t hi) {
            for (int64_t p = lo; p < hi; ++p) one(p);
          });
          return;
        }
        // Bands of rows per texture: key = texture * nb + band, class = band parity.
        const int64_t nb = band_count(H, taps_of<KIND>());
        std::vector<int32_t> classes(Bt * nb);
        for (int64_t i = 0; i < Bt * nb; ++i) classes[i] = nb > 1 ? static_cast<int32_t>(i % nb % 2) : 0;
        std::vector<int32_t> keys(B * M);
        at::parallel_for(0, B * M, 4096, [&](int64_t lo, int64_t hi) {
          for (int64_t p = lo; p < hi; ++p) {
            const scalar_t v = A.uv[2 * p + 1];
            if (!std::isfinite(A.uv[2 * p]) || !std::isfinite(v)) {
              keys[p] = -1;
              continue;
            }
            const int64_t r = first_row(line<KIND>(v, H, A.wrap_v), A.wrap_v);
            keys[p] = r < 0 ? -1 : static_cast<int32_t>((Bt == 1 ? 0 : p / M) * nb + band_of(r, H, nb));
            // Every tap on the border constant: no texel to scatter to, only the uv gradient.
            if (r < 0 && pguv != nullptr) backward_point<scalar_t, KIND, CC, kB>(p, A, pg, nullptr, pguv);
          }
        });
        run_banded(keys.data(), B * M, classes, one);
      });
    });
  });
  return {gt, guv};
}

}  // namespace difftex
