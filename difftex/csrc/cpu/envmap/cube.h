// The cube-map passes of the native CPU kernel (cube.cpp; difftex/envmap/cube.py's native path): the
// direction -> face / uv / trilinear length front end and the seamless bilinear-tap read of a cube pyramid.
// Declared apart from kernels.h so that only cube.cpp and module.cpp include them.
#pragma once

#include "stable.h"

#include <tuple>
#include <vector>

namespace difftex {

// mapping/common.py DIR_FLOOR / DIR_FLOOR_FLOAT32 (module.cpp exports them): the floor of a cube face's m_a
// by the inputs' dtype; cube.cpp says how a direction below it reads.
constexpr double kDirFloor = 1e-150, kDirFloorFloat = 1e-30;

// The front end, no graph: dirs [M, 3], dx / dy [M, 3] d(dirs) per pixel column / row (both empty: no
// level); bias [M] (empty: bias0), S the face size, levels the pyramid's, band envmap/cube.py EDGE_BAND.
// -> (face [M] int8, -1 for a zero and -2 for a non-finite direction; face uv [M, 2]; the level D [M]:
// lod.py level of the trilinear log2 length in face texels blended across edges as cube.py _log2_length;
// empty without dx / dy).
std::tuple<Tensor, Tensor, Tensor> cube_front(Tensor dirs, Tensor dx,
                                                                   Tensor dy, Tensor bias,
                                                                   double bias0, int64_t S, int64_t levels,
                                                                   double band);
// Its first-order backward from the gradients of uv [M, 2] and D [M] (empty: none) -> the gradients of
// dirs, dx, dy [M, 3] and bias [M] (dx, dy, bias undefined where not needed).
std::tuple<Tensor, Tensor, Tensor, Tensor> cube_front_backward(
    Tensor dirs, Tensor dx, Tensor dy, Tensor bias, double bias0, int64_t S,
    int64_t levels, double band, Tensor guv, Tensor gD, bool need_derivs, bool need_bias);

// The read: levels [6, C, n_k, n_k] of one cube; per level its gutter ring (1 texel around each face, ring
// order of cube.py _ring_tables) as 3 source texels (flat in [6, n_k, n_k]) [R_k, 3] int64 and weights
// [R_k, 3] float64; face [M] int8, uv [M, 2], D [M] (empty: level 0; nearest, d_grad as ReadOptions') ->
// [C, M]; backward -> (level gradients [6, C, n_k, n_k], undefined where unread or not needed; uv [M, 2];
// D [M]).
Tensor cube_read(std::vector<Tensor> levels, std::vector<Tensor> ring_idx,
                        std::vector<Tensor> ring_w, Tensor face, Tensor uv, Tensor D,
                        bool nearest, bool d_grad);
std::tuple<std::vector<Tensor>, Tensor, Tensor> cube_read_backward(
    std::vector<Tensor> levels, std::vector<Tensor> ring_idx, std::vector<Tensor> ring_w,
    Tensor face, Tensor uv, Tensor D, Tensor grad, bool nearest, bool d_grad,
    bool need_levels, bool need_uv, bool need_D);

}  // namespace difftex
