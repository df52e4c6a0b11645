// The box filters of the native CPU kernel: the summed-area table (sat.cpp;
// filters/sat.py's native path) and the ripmap (ripmap.cpp;
// filters/ripmap.py's). Declared apart from kernels.h (as cube.h is) so that
// only their sources and module.cpp include them.
#pragma once

#include "stable.h"

#include <tuple>
#include <vector>

#include "kernels.h"

namespace difftex {

// sat.cpp: the box sums of filters/sat.py _BoxSums of texture [C, H, W]
// (float32 / float64) at positions pu [M, Ku], pv [M, Kv] with coefficients
// cu, cv (float64, K <= 4). Forward -> {out [C, M] float64} or, with
// jacobians, {out, d out / d pu, d out / d cu [C, M, Ku], d out / d pv,
// d out / d cv [C, M, Kv]}; without coef_grads the coefficients'
// Jacobians are zero and terms with a zero coefficient are not read.
// Backward -> the texture's gradient [C, H, W] (its dtype) from grad [C, M]
// float64.
std::vector<Tensor> sat_forward(Tensor texture, Tensor pu, Tensor cu, Tensor pv,
                                       Tensor cv, bool jacobians, bool coef_grads);
Tensor sat_backward(Tensor texture, Tensor pu, Tensor cu, Tensor pv,
                           Tensor cv, Tensor grad);

// ripmap.cpp. Levels are a flat list, level (i, j) (i width halvings, j
// height halvings) at j * n_u + i, each [C, ceil(H / 2^j), ceil(W / 2^i)]
// or undefined where not built / not read.
//
// ripmap_build: the levels of texture [C, H, W] (pyramid/ripmap.py
// build_ripmap, the same halvings) for every (i, j) with wanted[j * n_u + i]
// and the levels on their way (column i = 0 up to row j, then row j up to
// i); the others undefined.
std::vector<Tensor> ripmap_build(Tensor texture, int64_t n_u, int64_t n_v, std::vector<bool> wanted);
// ripmap_adjoint: the texture's gradient [C, H, W] from the levels'
// gradients (empty: zero; consumed: the sums are formed in them), the
// transpose of ripmap_build.
Tensor ripmap_adjoint(std::vector<Tensor> grads, int64_t n_u, int64_t n_v, int64_t H, int64_t W);
// ripmap_read: filters/ripmap.py ripmap_points at uv [M, 2] and the levels
// Du, Dv [M] (clamped to [0, n - 1]): per axis the levels floor(D) and
// floor(D) + 1 (common.h reads_of with opts.d_grad), four bilinear reads
// blended -> [C, M], NaN where uv is not finite.
Tensor ripmap_read(std::vector<Tensor> levels, int64_t n_u, Tensor uv, Tensor Du,
                          Tensor Dv, const ReadOptions& opts);
// Its first-order backward: (level gradients, undefined where not read or
// not needed; uv [M, 2]; Du [M]; Dv [M]), each undefined where not needed.
std::tuple<std::vector<Tensor>, Tensor, Tensor, Tensor> ripmap_read_backward(
    std::vector<Tensor> levels, int64_t n_u, Tensor uv, Tensor Du, Tensor Dv,
    Tensor grad, const ReadOptions& opts, bool need_levels, bool need_uv, bool need_D);

}  // namespace difftex
