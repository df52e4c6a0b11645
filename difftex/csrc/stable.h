// What the CPU kernels take from torch: the LibTorch stable ABI only (torch >= 2.10), so that one build runs
// on every later torch without a rebuild, and each translation unit compiles in about a second of headers
// instead of the ~30 s of <torch/extension.h>. The kernels work on raw pointers; this header gives them the
// few tensor operations they need around that (allocation, contiguity, threads, checks), under the names
// they used before the move to the stable ABI, so that their arithmetic did not change.
#pragma once

#include <torch/csrc/stable/ops.h>
#include <torch/csrc/stable/tensor.h>
#include <torch/headeronly/core/ScalarType.h>
#include <torch/headeronly/util/Exception.h>

#include <cstdint>
#include <optional>
#include <vector>

namespace difftex {

using Tensor = torch::stable::Tensor;
using ScalarType = torch::headeronly::ScalarType;
using IntArrayRef = torch::headeronly::IntHeaderOnlyArrayRef;

constexpr ScalarType kFloat32 = ScalarType::Float;
constexpr ScalarType kFloat64 = ScalarType::Double;
constexpr ScalarType kInt64 = ScalarType::Long;
constexpr ScalarType kInt32 = ScalarType::Int;
constexpr ScalarType kInt8 = ScalarType::Char;

// A failed check throws std::runtime_error, which reaches Python as a RuntimeError with the message.
#define DT_CHECK(cond, ...) STD_TORCH_CHECK(cond, __VA_ARGS__)

// Runs the lambda with scalar_t = float or double by the dtype (the stable ABI's stand-in for
// AT_DISPATCH_FLOATING_TYPES, which needs ATen).
#define DT_DISPATCH_FLOATING_TYPES(TYPE, NAME, ...)                                                   \
  [&] {                                                                                             \
    switch (TYPE) {                                                                                 \
      case ::difftex::kFloat32: {                                                                   \
        using scalar_t = float;                                                                     \
        return __VA_ARGS__();                                                                       \
      }                                                                                             \
      case ::difftex::kFloat64: {                                                                   \
        using scalar_t = double;                                                                    \
        return __VA_ARGS__();                                                                       \
      }                                                                                             \
      default:                                                                                      \
        STD_TORCH_CHECK(false, NAME, ": expected float32 or float64, got dtype code ",              \
                        static_cast<int>(TYPE));                                                    \
    }                                                                                               \
  }()

// The dtype of a new tensor (every tensor here is on the CPU): options_of(x) is x's, .dtype(t) another.
struct Options {
  ScalarType type;
  /* implicit */ Options(ScalarType t) : type(t) {}
  Options dtype(ScalarType t) const { return Options(t); }
};

inline Options options_of(const Tensor& x) { return Options{x.scalar_type()}; }

inline Tensor empty(IntArrayRef sizes, Options o) {
  return torch::stable::empty(sizes, o.type, std::nullopt, torch::stable::Device(torch::headeronly::DeviceType::CPU));
}

inline Tensor zeros(IntArrayRef sizes, Options o) {
  Tensor t = empty(sizes, o);
  torch::stable::zero_(t);
  return t;
}

inline Tensor zeros_like(const Tensor& x) { return zeros(x.sizes(), options_of(x)); }

inline Tensor contig(const Tensor& x) { return x.is_contiguous() ? x : torch::stable::contiguous(x); }

// Whether a 4-d tensor [B, C, H, W] is stored channels-last (C innermost), as torch's
// is_contiguous(memory_format=torch.channels_last) says, for the sizes the kernels read.
inline bool is_channels_last(const Tensor& x) {
  if (x.dim() != 4) return false;
  const int64_t C = x.size(1), H = x.size(2), W = x.size(3);
  int64_t expect = 1;
  auto ok = [&](int64_t d, int64_t n) {
    const bool good = n == 1 || x.stride(d) == expect;
    expect *= n;
    return good;
  };
  return ok(1, C) && ok(3, W) && ok(2, H) && ok(0, x.size(0));
}

// An empty tensor of x's sizes and layout (contiguous or channels-last), zeroed.
inline Tensor zeros_in_layout_of(const Tensor& x) {
  if (x.is_contiguous() || !is_channels_last(x)) return zeros_like(x);
  Tensor t = torch::stable::empty(x.sizes(), x.scalar_type(), std::nullopt,
                                  torch::stable::Device(torch::headeronly::DeviceType::CPU), std::nullopt,
                                  torch::headeronly::MemoryFormat::ChannelsLast);
  torch::stable::zero_(t);
  return t;
}

// torch's intra-op threads: how many, and which one runs the caller (0 outside a parallel region).
inline int64_t get_num_threads() { return static_cast<int64_t>(torch::stable::get_num_threads()); }

inline int64_t get_thread_num() {
  uint32_t idx = 0;
  STABLE_TORCH_ERROR_CODE_CHECK(torch_get_thread_idx(&idx));
  return static_cast<int64_t>(idx);
}

// torch's at::parallel_for through the stable ABI: the same chunks, so the same results at any thread count.
template <class F>
inline void parallel_for(int64_t begin, int64_t end, int64_t grain, const F& f) {
  torch::stable::parallel_for(begin, end, grain, f);
}

}  // namespace difftex
