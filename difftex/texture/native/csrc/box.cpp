// The pyramid's 2 x 2 box step on the CPU (texture/pyramid/mipmap.py _box2)
// and its transpose (mipmap.py step_adjoint).
#include "kernels.h"

namespace difftex {

// One 2 x 2 box step of an even x even level (pyramid/mipmap.py _box2, the
// same sums in the same order, so bit-identical): [..., H, W] -> [..., H/2,
// W/2]. One pass over the level instead of torch's three (two strided adds
// and a scale): about half the memory traffic of the pyramid build.
torch::Tensor box2(torch::Tensor x) {
  TORCH_CHECK(x.dim() >= 2 && x.size(-2) % 2 == 0 && x.size(-1) % 2 == 0 && x.device().is_cpu(),
              "mip_read.box2: expected a CPU tensor [..., H, W] with even H and W");
  x = x.contiguous();
  const int64_t H = x.size(-2), W = x.size(-1), h = H / 2, w = W / 2;
  auto sizes = x.sizes().vec();
  sizes[sizes.size() - 2] = h;
  sizes[sizes.size() - 1] = w;
  auto out = torch::empty(sizes, x.options());
  const int64_t rows = x.numel() / W / 2;  // output rows over every plane
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "mip_read_box2", [&] {
    const scalar_t* px = x.data_ptr<scalar_t>();
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, rows, 16, [&](int64_t lo, int64_t hi) {
      for (int64_t r = lo; r < hi; ++r) {
        const scalar_t* a = px + 2 * r * W;
        const scalar_t* b = a + W;
        scalar_t* o = po + r * w;
        for (int64_t j = 0; j < w; ++j)
          o[j] = ((a[2 * j] + a[2 * j + 1]) + (b[2 * j] + b[2 * j + 1])) * static_cast<scalar_t>(0.25);
      }
    });
  });
  return out;
}

// The transpose of box2 (pyramid/mipmap.py step_adjoint, even sides):
// fine + coarse / 4 on each 2 x 2 block, [..., h, w] -> [..., 2h, 2w], fine
// undefined reading as zeros. The same sums as the torch path
// (bit-identical), in one pass that writes the fine gradient once: torch's
// nearest upsampling took 2.2-2.5x as long at 512^2 -> 1024^2 x 3.
torch::Tensor box2_adjoint(torch::Tensor coarse, c10::optional<torch::Tensor> fine) {
  TORCH_CHECK(coarse.dim() >= 2 && coarse.device().is_cpu(), "mip_read.box2_adjoint: expected a CPU tensor [..., h, w]");
  coarse = coarse.contiguous();
  const int64_t h = coarse.size(-2), w = coarse.size(-1), W = 2 * w;
  auto sizes = coarse.sizes().vec();
  sizes[sizes.size() - 2] = 2 * h;
  sizes[sizes.size() - 1] = W;
  const bool add = fine.has_value() && fine->defined();
  torch::Tensor f;
  if (add) {
    TORCH_CHECK(fine->sizes() == torch::IntArrayRef(sizes) && fine->scalar_type() == coarse.scalar_type() &&
                    fine->device().is_cpu(), "mip_read.box2_adjoint: fine must be [..., 2h, 2w] of coarse's dtype");
    f = fine->contiguous();
  }
  auto out = torch::empty(sizes, coarse.options());
  const int64_t rows = coarse.numel() / w;  // coarse rows over every plane
  AT_DISPATCH_FLOATING_TYPES(coarse.scalar_type(), "mip_read_box2_adjoint", [&] {
    const scalar_t* pc = coarse.data_ptr<scalar_t>();
    const scalar_t* pf = add ? f.data_ptr<scalar_t>() : nullptr;
    scalar_t* po = out.data_ptr<scalar_t>();
    at::parallel_for(0, rows, 16, [&](int64_t lo, int64_t hi) {
      for (int64_t r = lo; r < hi; ++r) {
        const scalar_t* c = pc + r * w;
        for (int64_t half = 0; half < 2; ++half) {
          scalar_t* o = po + (2 * r + half) * W;
          if (pf == nullptr) {
            for (int64_t j = 0; j < w; ++j) o[2 * j] = o[2 * j + 1] = static_cast<scalar_t>(0.25) * c[j];
          } else {
            const scalar_t* a = pf + (2 * r + half) * W;
            for (int64_t j = 0; j < w; ++j) {
              const scalar_t q = static_cast<scalar_t>(0.25) * c[j];
              o[2 * j] = a[2 * j] + q;
              o[2 * j + 1] = a[2 * j + 1] + q;
            }
          }
        }
      }
    });
  });
  return out;
}

}  // namespace difftex
