// The pyramid's 2 x 2 box step on the CPU (texture/pyramid/mipmap.py _box2).
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

}  // namespace difftex
