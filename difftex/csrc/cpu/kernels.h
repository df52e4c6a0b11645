// The entry points of the native CPU kernel (difftex/texture/native), one
// source each, and the options they take by name: module.cpp binds them,
// the Python callers (filters/trilinear.py _NativeTaps, filters/ewa.py
// _NativeEWA, taps.py, pyramid/mipmap.py) fill the options by keyword, so
// no caller counts boolean positions.
#pragma once

#include "stable.h"

#include <tuple>
#include <vector>

namespace difftex {

// How a pyramid read treats the texture: the wrap code of each axis
// (texture/wrap.py WRAP_CODES), the constant read outside for "border",
// nearest-mip (one level, the nearest) or a blend of two, and whether D
// needs a gradient (mip_blend then reads the upper level at an integer D
// too, for d/dD).
struct ReadOptions {
  int64_t wrap_u, wrap_v;
  double border;
  bool nearest, d_grad;
  // Stochastic trilinear filtering (filters/stochastic.py): instead of the
  // filter, one draw a point (one tap, no counts): one level drawn by the
  // defensive blend pmf, read bilinearly and weighted w(D) / p. Point e's
  // uniform is common.h stratified_uniform(seed, first + e, strata) (the
  // same counter as its torch reference, so that the two draw alike).
  bool stochastic = false;
  uint64_t seed = 0;
  int64_t first = 0, strata = 1;
};

// The gradients the taps' backward computes.
struct TapNeeds {
  bool levels, uv, D, axis;
};

// The gradients the EWA backward computes (ellipse: sigma, minor and scale).
struct EwaNeeds {
  bool levels, uv, ellipse, D;
};

// taps.cpp: the bilinear-tap mip filters. Levels [C, h_k, w_k], uv [M, 2],
// D [M], axis [M, 2] and count [M] int64 (both empty: one tap a point);
// forward -> [C, M]; backward -> (level gradients, undefined where no point
// reads the level or not needed; uv [M, 2]; D [M]; axis [M, 2]), each
// undefined where not needed.
Tensor forward(std::vector<Tensor> levels, Tensor uv, Tensor D, Tensor axis,
                      Tensor count, const ReadOptions& opts);
std::tuple<std::vector<Tensor>, Tensor, Tensor, Tensor> backward(
    std::vector<Tensor> levels, Tensor uv, Tensor D, Tensor axis, Tensor count,
    Tensor grad, const ReadOptions& opts, const TapNeeds& need);

// taps.cpp: the probe of one stochastic anisotropic draw per point, as its
// offset along the axis (tap_offset of probe floor(u N) of N = count[e], u
// = stratified_uniform(seed, first + e, strata)): [M] in like's dtype.
Tensor probe_offsets(Tensor count, Tensor like, uint64_t seed, int64_t first, int64_t strata);

// front.cpp: the taps' footprint front end, no gradient.
std::tuple<Tensor, Tensor, Tensor> front(Tensor dx, Tensor dy, Tensor bias,
                                                              double bias0, int64_t H, int64_t W, int64_t levels,
                                                              int64_t kind, double max_aniso, double tolerance);

// box.cpp: one 2 x 2 box step of the pyramid.
Tensor box2(Tensor x);
Tensor box2_adjoint(Tensor coarse, std::optional<Tensor> fine);

// ewa.cpp: EWA, forward [C, M] and first-order backward.
Tensor ewa(std::vector<Tensor> levels, Tensor uv, Tensor sigma, Tensor minor,
                  Tensor scale, Tensor D, int64_t full_h, int64_t full_w, const ReadOptions& opts);
std::tuple<std::vector<Tensor>, Tensor, Tensor, Tensor, Tensor, Tensor>
ewa_backward(std::vector<Tensor> levels, Tensor uv, Tensor sigma, Tensor minor,
             Tensor scale, Tensor D, Tensor grad, int64_t full_h, int64_t full_w,
             const ReadOptions& opts, const EwaNeeds& need);

// raster.cpp: rasterize's visibility pass (geometry/raster.py _visibility).
// pos [B, V, 4] float32 / float64 (computed in float64), faces [F, 3] int64; bits: sub-pixel bits of the
// exact path (0: float path only); floor_z / floor_id [B * H * W] or empty
// (depth peeling). -> (ids [B * H * W] int64, -1 background, or with count
// the number of covering fragments; depth [B * H * W] float64, +inf
// background). With layers K > 1 (no floor, no count) the K nearest
// fragments per pixel in (depth, id) order: ids [K * B * H * W] layer-major,
// and the K-th layer's depth [B * H * W].
// Empty tensors where pos holds a non-finite value or faces an index
// outside [0, V) (the caller's checks then name it).
std::tuple<Tensor, Tensor> raster(Tensor pos, Tensor faces, int64_t H, int64_t W,
                                                bool cull, int64_t bits, Tensor floor_z,
                                                Tensor floor_id, bool count, int64_t layers);
// raster.cpp: rasterize's differentiable pass, forward (geometry/raster.py
// fragments_of; the torch _bary_at gives the gradients). pos [B, V, 4]
// float, faces [F, 3] int64, tri_id [B, H, W] int64 (-1 background) ->
// (idx [N] flat covered pixels, bary, bary_dx, bary_dy [N, 3] there, dense
// bary [B, H, W, 3], depth [B, H, W], bary_dx, bary_dy [B, H, W, 3]); with
// packed, nvdiffrast's layout instead: (idx, rast [B, H, W, 4] = (b0, b1,
// depth, id + 1 + offset), db [B, H, W, 4] = (db0/dx, db0/dy, db1/dx,
// db1/dy)); zeros on background. Without derivatives the bary_dx, bary_dy
// (or db) outputs are empty [0] tensors and cost nothing.
std::vector<Tensor> raster_fragments(Tensor pos, Tensor faces, Tensor tri_id,
                                            bool packed, int64_t offset, bool derivatives);
// raster.cpp: raster (no floor, no count) and raster_fragments (unpacked) of
// each of its layers in one pass, each band's fragments computed right
// after its z-buffer (k-buffer): (ids [B * H * W] of each of the K layers,
// depth [B * H * W] float64 or, without keep_depth, empty, then per layer
// raster_fragments'
// outputs: idx, bary, bary_dx, bary_dy [N, 3], bary [B, H, W, 3], depth
// [B, H, W], bary_dx, bary_dy [B, H, W, 3]); the same values as the
// separate calls. Just (ids, depth), both empty, where raster would return
// empty tensors.
std::vector<Tensor> raster_fused(Tensor pos, Tensor faces, int64_t H, int64_t W, bool cull, int64_t bits,
                                 bool derivatives, bool keep_depth, int64_t layers);
// Its first-order backward: the output gradients as autograd gives them
// (compact and dense, or packed; undefined: none) -> the gradient of pos.
Tensor raster_fragments_backward(Tensor pos, Tensor faces, Tensor tri_id,
                                        Tensor idx, std::vector<Tensor> grads, bool packed);

// single.cpp: the single-level reads (kind 0 nearest, 1 bilinear, 2
// bicubic; wrap and border from opts) of texture [Bt, C, H, W] at uv
// [B, *S, 2] (Bt = 1 or B; S any pixel shape, M = prod(S) points an entry):
// forward -> [B, C, *S]; first-order backward (grad [B, C, *S]) ->
// (texture gradient, uv gradient), each undefined where not needed.
Tensor sample(Tensor texture, Tensor uv, int64_t kind, const ReadOptions& opts);
std::tuple<Tensor, Tensor> sample_backward(Tensor texture, Tensor uv, Tensor grad,
                                                         int64_t kind, const ReadOptions& opts, bool need_texture,
                                                         bool need_uv);
// Whether float32 reads (single.cpp's bilinear / bicubic, taps.cpp's one
// tap a point) use the eight-point AVX2 paths, on by default where the CPU
// has them: set_simd sets it and returns the previous setting (the tests
// run both paths against the reference); simd_available says whether this
// CPU has them. The same switch turns raster.cpp's four-vertex and eight-
// triangle AVX2 passes (same bits as its scalar loops, tested both ways).
bool set_simd(bool enabled);
bool simd_available();
// Whether single.cpp's float32 bilinear / bicubic forward reads sixteen
// points at a time (AVX-512; same bits as the eight-point path), on by
// default where the CPU has AVX512F / AVX512DQ and set_simd is on: set_wide
// sets it and returns the previous setting; wide_available says whether
// this CPU has it.
bool set_wide(bool enabled);
bool wide_available();
// Whether that sixteen-point forward writes an output of 1 MB or more with
// non-temporal stores (same bits either way; on by default): set_stream
// sets it and returns the previous setting, for the tests and the benchmark.
bool set_stream(bool enabled);

}  // namespace difftex
