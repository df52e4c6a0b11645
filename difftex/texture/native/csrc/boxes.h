// The box filters of the native CPU kernel: the summed-area table (sat.cpp;
// filters/sat.py's native path) and the ripmap (ripmap.cpp;
// filters/ripmap.py's). Declared apart from kernels.h (as cube.h is) so that
// only their sources and module.cpp include them.
#pragma once

#include <torch/extension.h>

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
std::vector<torch::Tensor> sat_forward(torch::Tensor texture, torch::Tensor pu, torch::Tensor cu, torch::Tensor pv,
                                       torch::Tensor cv, bool jacobians, bool coef_grads);
torch::Tensor sat_backward(torch::Tensor texture, torch::Tensor pu, torch::Tensor cu, torch::Tensor pv,
                           torch::Tensor cv, torch::Tensor grad);

// ripmap.cpp. Levels are a flat list, level (i, j) (i width halvings, j
// height halvings) at j * n_u + i, each [C, ceil(H / 2^j), ceil(W / 2^i)]
// or undefined where not built / not read.
//
// ripmap_build: the levels of texture [C, H, W] (pyramid/ripmap.py
// build_ripmap, the same halvings) for every (i, j) with wanted[j * n_u + i]
// and the levels on their way (column i = 0 up to row j, then row j up to
// i); the others undefined.
std::vector<torch::Tensor> ripmap_build(torch::Tensor texture, int64_t n_u, int64_t n_v, std::vector<bool> wanted);
// ripmap_adjoint: the texture's gradient [C, H, W] from the levels'
// gradients (empty: zero; consumed: the sums are formed in them), the
// transpose of ripmap_build.
torch::Tensor ripmap_adjoint(std::vector<torch::Tensor> grads, int64_t n_u, int64_t n_v, int64_t H, int64_t W);
// ripmap_read: filters/ripmap.py ripmap_points at uv [M, 2] and the levels
// Du, Dv [M] (clamped to [0, n - 1]): per axis the levels floor(D) and
// floor(D) + 1 (common.h reads_of with opts.d_grad), four bilinear reads
// blended -> [C, M], NaN where uv is not finite.
torch::Tensor ripmap_read(std::vector<torch::Tensor> levels, int64_t n_u, torch::Tensor uv, torch::Tensor Du,
                          torch::Tensor Dv, const ReadOptions& opts);
// Its first-order backward: (level gradients, undefined where not read or
// not needed; uv [M, 2]; Du [M]; Dv [M]), each undefined where not needed.
std::tuple<std::vector<torch::Tensor>, torch::Tensor, torch::Tensor, torch::Tensor> ripmap_read_backward(
    std::vector<torch::Tensor> levels, int64_t n_u, torch::Tensor uv, torch::Tensor Du, torch::Tensor Dv,
    torch::Tensor grad, const ReadOptions& opts, bool need_levels, bool need_uv, bool need_D);

}  // namespace difftex
