// The pyramid's 2 x 2 box step on the CPU (texture/pyramid/mipmap.py _box2)
// and its transpose (mipmap.py step_adjoint).
#include "kernels.h"

namespace difftex {

// One 2 x 2 box step of an even x even level (pyramid/mipmap.py _box2, the
// same sums in the same order, so bit-identical): [..., H, W] -> [..., H/2,
// W/2]. One pass over the level instead of torch's three (two strided adds
// and a scale): about half the memory traffic of the pyramid build.
Tensor box2(Tensor x) {
  DT_CHECK(x.dim() >= 2 && x.size(-2) % 2 == 0 && x.size(-1) % 2 == 0 && x.is_cpu(),
              "mip_read.box2: expected a CPU tensor [..., H, W] with even H and W");
  x = contig(x);
  const int64_t H = x.size(-2), W = x.size(-1), h = H / 2, w = W / 2;
  auto sizes = x.sizes().vec();
  sizes[sizes.size() - 2] = h;
  sizes[sizes.size() - 1] = w;
  auto out = empty(sizes, options_of(x));
  const int64_t rows = x.numel() / W / 2;  // output rows over every plane
  DT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "mip_read_box2", [&] {
    const scalar_t* px = x.mutable_data_ptr<scalar_t>();
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    parallel_for(0, rows, 16, [&](int64_t lo, int64_t hi) {
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
Tensor box2_adjoint(Tensor coarse, std::optional<Tensor> fine) {
  DT_CHECK(coarse.dim() >= 2 && coarse.is_cpu(), "mip_read.box2_adjoint: expected a CPU tensor [..., h, w]");
  coarse = contig(coarse);
  const int64_t h = coarse.size(-2), w = coarse.size(-1), W = 2 * w;
  auto sizes = coarse.sizes().vec();
  sizes[sizes.size() - 2] = 2 * h;
  sizes[sizes.size() - 1] = W;
  const bool add = fine.has_value() && fine->defined();
  Tensor f;
  if (add) {
    DT_CHECK(fine->sizes() == IntArrayRef(sizes) && fine->scalar_type() == coarse.scalar_type() &&
                    fine->is_cpu(), "mip_read.box2_adjoint: fine must be [..., 2h, 2w] of coarse's dtype");
    f = contig(*fine);
  }
  auto out = empty(sizes, options_of(coarse));
  const int64_t rows = coarse.numel() / w;  // coarse rows over every plane
  DT_DISPATCH_FLOATING_TYPES(coarse.scalar_type(), "mip_read_box2_adjoint", [&] {
    const scalar_t* pc = coarse.mutable_data_ptr<scalar_t>();
    const scalar_t* pf = add ? f.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    parallel_for(0, rows, 16, [&](int64_t lo, int64_t hi) {
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
