// The registration of difftex's native CPU kernels as torch operators (torch.ops.difftex.*) through the
// LibTorch stable ABI, and the Python module difftex._C whose import loads them. The only translation unit
// that knows the schemas; the kernels (cpu/) take their options as structs and return undefined tensors
// for what was not asked for, which the schemas give back as None (Tensor?).
//
// difftex/_native.py is the Python side: it imports difftex._C, calls the operators by these names, and
// registers the fake (meta) implementations that torch.compile and torch.library.opcheck use.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <torch/csrc/stable/library.h>

#include <optional>
#include <tuple>
#include <vector>

#include "boxes.h"
#include "common.h"
#include "envmap/cube.h"
#include "kernels.h"
#include "stable.h"

using namespace difftex;

namespace {

using OptTensor = std::optional<Tensor>;
using OptTensors = std::vector<std::optional<Tensor>>;

OptTensor opt(const Tensor& t) { return t.defined() ? OptTensor(t) : std::nullopt; }

OptTensors opts(const std::vector<Tensor>& ts) {
  OptTensors out;
  out.reserve(ts.size());
  for (const auto& t : ts) out.push_back(opt(t));
  return out;
}

// A backward's level gradients as a list of tensors: where a level was not read (or not asked for), a
// tensor with no rows ([0, ...] of that level's other sizes), which difftex/_native.py turns into None. Its
// fake implementation can then give every level a gradient whose first size is data-dependent.
std::vector<Tensor> level_list(const std::vector<Tensor>& gl, const std::vector<std::vector<int64_t>>& shapes,
                               ScalarType dtype) {
  std::vector<Tensor> out;
  out.reserve(gl.size());
  for (size_t k = 0; k < gl.size(); ++k) {
    if (gl[k].defined()) {
      out.push_back(gl[k]);
    } else {
      std::vector<int64_t> s = shapes[k];
      if (s.empty()) s.push_back(0);
      s[0] = 0;
      out.push_back(empty(s, dtype));
    }
  }
  return out;
}

std::vector<std::vector<int64_t>> shapes_of(const std::vector<Tensor>& ts) {
  std::vector<std::vector<int64_t>> out;
  for (const auto& t : ts) out.push_back(t.sizes().vec());
  return out;
}

ReadOptions read_options(int64_t wrap_u, int64_t wrap_v, double border, bool nearest, bool d_grad) {
  DT_CHECK(wrap_u >= REPEAT && wrap_u <= BORDER, "difftex: wrap_u must be a wrap code 0-3, got ", wrap_u);
  DT_CHECK(wrap_v >= REPEAT && wrap_v <= BORDER, "difftex: wrap_v must be a wrap code 0-3, got ", wrap_v);
  return ReadOptions{wrap_u, wrap_v, border, nearest, d_grad};
}

// taps.cpp
Tensor taps_forward(std::vector<Tensor> levels, Tensor uv, Tensor D, Tensor axis, Tensor count, int64_t wrap_u,
                    int64_t wrap_v, double border, bool nearest, bool d_grad) {
  return forward(std::move(levels), uv, D, axis, count, read_options(wrap_u, wrap_v, border, nearest, d_grad));
}

std::tuple<std::vector<Tensor>, OptTensor, OptTensor, OptTensor> taps_backward(
    std::vector<Tensor> levels, Tensor uv, Tensor D, Tensor axis, Tensor count, Tensor grad, int64_t wrap_u,
    int64_t wrap_v, double border, bool nearest, bool d_grad, bool need_levels, bool need_uv, bool need_D,
    bool need_axis) {
  const auto shapes = shapes_of(levels);
  auto [gl, guv, gD, gax] = backward(std::move(levels), uv, D, axis, count, grad,
                                     read_options(wrap_u, wrap_v, border, nearest, d_grad),
                                     TapNeeds{need_levels, need_uv, need_D, need_axis});
  return {level_list(gl, shapes, uv.scalar_type()), opt(guv), opt(gD), opt(gax)};
}

// taps.cpp, stochastic: one trilinear draw a point (ReadOptions::stochastic), its uniform hashed from
// (seed, point) inside the kernel and stratified over the strata draws of a point. seed is the int64 that
// filters/stochastic.py draws from the torch generator (its bits taken as unsigned).
ReadOptions stochastic_options(int64_t seed, int64_t first, int64_t strata, int64_t wrap_u, int64_t wrap_v,
                               double border) {
  DT_CHECK(first >= 0, "difftex: first must be >= 0, got ", first);
  DT_CHECK(strata >= 1, "difftex: strata must be >= 1, got ", strata);
  ReadOptions o = read_options(wrap_u, wrap_v, border, false, false);
  o.stochastic = true;
  o.seed = static_cast<uint64_t>(seed);
  o.first = first;
  o.strata = strata;
  return o;
}

Tensor stochastic_taps_forward(std::vector<Tensor> levels, Tensor uv, Tensor D, int64_t seed, int64_t first,
                               int64_t strata, int64_t wrap_u, int64_t wrap_v, double border) {
  const Tensor none = empty({0}, kInt64);
  return forward(std::move(levels), uv, D, empty({0}, uv.scalar_type()), none,
                 stochastic_options(seed, first, strata, wrap_u, wrap_v, border));
}

std::tuple<std::vector<Tensor>, OptTensor, OptTensor> stochastic_taps_backward(
    std::vector<Tensor> levels, Tensor uv, Tensor D, Tensor grad, int64_t seed, int64_t first, int64_t strata,
    int64_t wrap_u, int64_t wrap_v, double border, bool need_levels, bool need_uv, bool need_D) {
  const auto shapes = shapes_of(levels);
  const Tensor none = empty({0}, kInt64);
  auto [gl, guv, gD, gax] = backward(std::move(levels), uv, D, empty({0}, uv.scalar_type()), none, grad,
                                     stochastic_options(seed, first, strata, wrap_u, wrap_v, border),
                                     TapNeeds{need_levels, need_uv, need_D, false});
  return {level_list(gl, shapes, uv.scalar_type()), opt(guv), opt(gD)};
}

Tensor probe_offsets_op(Tensor count, Tensor like, int64_t seed, int64_t first, int64_t strata) {
  return probe_offsets(count, like, static_cast<uint64_t>(seed), first, strata);
}

// front.cpp
std::tuple<Tensor, Tensor, Tensor> tap_front(Tensor dx, Tensor dy, Tensor bias, double bias0, int64_t H, int64_t W,
                                             int64_t levels, int64_t kind, double max_aniso, double tolerance) {
  return front(dx, dy, bias, bias0, H, W, levels, kind, max_aniso, tolerance);
}

// box.cpp
Tensor box2_op(Tensor x) { return box2(x); }
Tensor box2_adjoint_op(Tensor coarse, OptTensor fine) { return box2_adjoint(coarse, fine); }

// ewa.cpp
Tensor ewa_forward(std::vector<Tensor> levels, Tensor uv, Tensor sigma, Tensor minor, Tensor scale, Tensor D,
                   int64_t full_h, int64_t full_w, int64_t wrap_u, int64_t wrap_v, double border, bool d_grad) {
  return ewa(std::move(levels), uv, sigma, minor, scale, D, full_h, full_w,
             read_options(wrap_u, wrap_v, border, false, d_grad));
}

std::tuple<std::vector<Tensor>, OptTensor, OptTensor, OptTensor, OptTensor, OptTensor> ewa_backward_op(
    std::vector<Tensor> levels, Tensor uv, Tensor sigma, Tensor minor, Tensor scale, Tensor D, Tensor grad,
    int64_t full_h, int64_t full_w, int64_t wrap_u, int64_t wrap_v, double border, bool d_grad, bool need_levels,
    bool need_uv, bool need_ellipse, bool need_D) {
  const auto shapes = shapes_of(levels);
  auto [gl, guv, gsig, gmin, gsc, gD] =
      ewa_backward(std::move(levels), uv, sigma, minor, scale, D, grad, full_h, full_w,
                   read_options(wrap_u, wrap_v, border, false, d_grad),
                   EwaNeeds{need_levels, need_uv, need_ellipse, need_D});
  return {level_list(gl, shapes, uv.scalar_type()), opt(guv), opt(gsig), opt(gmin), opt(gsc), opt(gD)};
}

// single.cpp
Tensor sample_forward(Tensor texture, Tensor uv, int64_t kind, int64_t wrap_u, int64_t wrap_v, double border) {
  return sample(texture, uv, kind, read_options(wrap_u, wrap_v, border, false, false));
}

std::tuple<OptTensor, OptTensor> sample_backward_op(Tensor texture, Tensor uv, Tensor grad, int64_t kind,
                                                    int64_t wrap_u, int64_t wrap_v, double border,
                                                    bool need_texture, bool need_uv) {
  auto [gt, guv] = sample_backward(texture, uv, grad, kind, read_options(wrap_u, wrap_v, border, false, false),
                                   need_texture, need_uv);
  return {opt(gt), opt(guv)};
}

// raster.cpp
std::tuple<Tensor, Tensor> raster_op(Tensor pos, Tensor faces, int64_t H, int64_t W, bool cull, int64_t bits,
                                     Tensor floor_z, Tensor floor_id, bool count, int64_t layers) {
  return raster(pos, faces, H, W, cull, bits, floor_z, floor_id, count, layers);
}

std::vector<Tensor> raster_fragments_op(Tensor pos, Tensor faces, Tensor tri_id, bool packed, int64_t offset,
                                        bool derivatives) {
  return raster_fragments(pos, faces, tri_id, packed, offset, derivatives);
}

std::vector<Tensor> raster_fused_op(Tensor pos, Tensor faces, int64_t H, int64_t W, bool cull, int64_t bits,
                                    bool derivatives, bool keep_depth, int64_t layers) {
  return raster_fused(pos, faces, H, W, cull, bits, derivatives, keep_depth, layers);
}

Tensor raster_fragments_backward_op(Tensor pos, Tensor faces, Tensor tri_id, Tensor idx, OptTensors grads,
                                    bool packed) {
  std::vector<Tensor> g;
  g.reserve(grads.size());
  for (auto& t : grads) g.push_back(t.has_value() ? *t : Tensor());
  return raster_fragments_backward(pos, faces, tri_id, idx, std::move(g), packed);
}

// cube.cpp
std::tuple<Tensor, Tensor, Tensor> cube_front_op(Tensor dirs, Tensor dx, Tensor dy, Tensor bias, double bias0,
                                                 int64_t S, int64_t levels, double band) {
  return cube_front(dirs, dx, dy, bias, bias0, S, levels, band);
}

std::tuple<Tensor, OptTensor, OptTensor, OptTensor> cube_front_backward_op(
    Tensor dirs, Tensor dx, Tensor dy, Tensor bias, double bias0, int64_t S, int64_t levels, double band,
    Tensor guv, Tensor gD, bool need_derivs, bool need_bias) {
  auto [gd, gx, gy, gb] = cube_front_backward(dirs, dx, dy, bias, bias0, S, levels, band, guv, gD, need_derivs,
                                              need_bias);
  return {gd, opt(gx), opt(gy), opt(gb)};
}

Tensor cube_read_op(std::vector<Tensor> levels, std::vector<Tensor> ring_idx, std::vector<Tensor> ring_w,
                    Tensor face, Tensor uv, Tensor D, bool nearest, bool d_grad) {
  return cube_read(std::move(levels), std::move(ring_idx), std::move(ring_w), face, uv, D, nearest, d_grad);
}

std::tuple<std::vector<Tensor>, OptTensor, OptTensor> cube_read_backward_op(
    std::vector<Tensor> levels, std::vector<Tensor> ring_idx, std::vector<Tensor> ring_w, Tensor face, Tensor uv,
    Tensor D, Tensor grad, bool nearest, bool d_grad, bool need_levels, bool need_uv, bool need_D) {
  const auto shapes = shapes_of(levels);
  auto [gl, guv, gD] = cube_read_backward(std::move(levels), std::move(ring_idx), std::move(ring_w), face, uv, D,
                                          grad, nearest, d_grad, need_levels, need_uv, need_D);
  return {level_list(gl, shapes, uv.scalar_type()), opt(guv), opt(gD)};
}

// sat.cpp
std::vector<Tensor> sat_forward_op(Tensor texture, Tensor pu, Tensor cu, Tensor pv, Tensor cv, bool jacobians,
                                   bool coef_grads) {
  return sat_forward(texture, pu, cu, pv, cv, jacobians, coef_grads);
}

Tensor sat_backward_op(Tensor texture, Tensor pu, Tensor cu, Tensor pv, Tensor cv, Tensor grad) {
  return sat_backward(texture, pu, cu, pv, cv, grad);
}

// ripmap.cpp
OptTensors ripmap_build_op(Tensor texture, int64_t n_u, int64_t n_v, std::vector<int64_t> wanted) {
  std::vector<bool> w(wanted.begin(), wanted.end());
  OptTensors out = opts(ripmap_build(texture, n_u, n_v, std::move(w)));
  // Level (0, 0) is the texture itself where it is contiguous: an output may not alias an input, so None
  // comes back and difftex/_native.py puts the texture there.
  if (!out.empty() && out[0].has_value() && out[0]->data_ptr() == texture.data_ptr()) out[0] = std::nullopt;
  return out;
}

Tensor ripmap_adjoint_op(std::vector<Tensor> grads, int64_t n_u, int64_t n_v, int64_t H, int64_t W) {
  std::vector<const void*> inputs;
  for (const auto& g : grads) inputs.push_back(g.defined() ? g.data_ptr() : nullptr);
  Tensor out = ripmap_adjoint(std::move(grads), n_u, n_v, H, W);
  // The sums are formed in the levels' gradients (the schema marks them mutated); where the result is one of
  // them (a texture with no level above its own), a copy: an output may not alias an input.
  for (const void* p : inputs)
    if (p != nullptr && p == out.data_ptr()) return torch::stable::clone(out);
  return out;
}

Tensor ripmap_read_op(std::vector<Tensor> levels, int64_t n_u, Tensor uv, Tensor Du, Tensor Dv, int64_t wrap_u,
                      int64_t wrap_v, double border, bool d_grad) {
  return ripmap_read(std::move(levels), n_u, uv, Du, Dv, read_options(wrap_u, wrap_v, border, false, d_grad));
}

std::tuple<std::vector<Tensor>, OptTensor, OptTensor, OptTensor> ripmap_read_backward_op(
    std::vector<Tensor> levels, int64_t n_u, Tensor uv, Tensor Du, Tensor Dv, Tensor grad, int64_t wrap_u,
    int64_t wrap_v, double border, bool d_grad, bool need_levels, bool need_uv, bool need_D) {
  const auto shapes = shapes_of(levels);
  auto [gl, guv, gu, gv] =
      ripmap_read_backward(std::move(levels), n_u, uv, Du, Dv, grad,
                           read_options(wrap_u, wrap_v, border, false, d_grad), need_levels, need_uv, need_D);
  return {level_list(gl, shapes, uv.scalar_type()), opt(guv), opt(gu), opt(gv)};
}

}  // namespace

// The schemas (what torch.compile, opcheck and the fake implementations in difftex/_native.py see). Read
// options are flat: wrap codes (texture/wrap.py WRAP_CODES), the border constant, nearest-mip and whether
// the level D needs a gradient.
STABLE_TORCH_LIBRARY(difftex, m) {
  m.def("taps_forward(Tensor[] levels, Tensor uv, Tensor D, Tensor axis, Tensor count, int wrap_u, int wrap_v, "
        "float border, bool nearest, bool d_grad) -> Tensor");
  m.def("taps_backward(Tensor[] levels, Tensor uv, Tensor D, Tensor axis, Tensor count, Tensor grad, int wrap_u, "
        "int wrap_v, float border, bool nearest, bool d_grad, bool need_levels, bool need_uv, bool need_D, "
        "bool need_axis) -> (Tensor[], Tensor?, Tensor?, Tensor?)");
  m.def("stochastic_taps_forward(Tensor[] levels, Tensor uv, Tensor D, int seed, int first, int strata, "
        "int wrap_u, int wrap_v, float border) -> Tensor");
  m.def("stochastic_taps_backward(Tensor[] levels, Tensor uv, Tensor D, Tensor grad, int seed, int first, "
        "int strata, int wrap_u, int wrap_v, float border, bool need_levels, bool need_uv, bool need_D) "
        "-> (Tensor[], Tensor?, Tensor?)");
  m.def("probe_offsets(Tensor count, Tensor like, int seed, int first, int strata) -> Tensor");
  m.def("tap_front(Tensor dx, Tensor dy, Tensor bias, float bias0, int H, int W, int levels, int kind, "
        "float max_aniso, float tolerance) -> (Tensor, Tensor, Tensor)");
  m.def("box2(Tensor x) -> Tensor");
  m.def("box2_adjoint(Tensor coarse, Tensor? fine) -> Tensor");
  m.def("ewa_forward(Tensor[] levels, Tensor uv, Tensor sigma, Tensor minor, Tensor scale, Tensor D, int full_h, "
        "int full_w, int wrap_u, int wrap_v, float border, bool d_grad) -> Tensor");
  m.def("ewa_backward(Tensor[] levels, Tensor uv, Tensor sigma, Tensor minor, Tensor scale, Tensor D, "
        "Tensor grad, int full_h, int full_w, int wrap_u, int wrap_v, float border, bool d_grad, "
        "bool need_levels, bool need_uv, bool need_ellipse, bool need_D) "
        "-> (Tensor[], Tensor?, Tensor?, Tensor?, Tensor?, Tensor?)");
  m.def("sample_forward(Tensor texture, Tensor uv, int kind, int wrap_u, int wrap_v, float border) -> Tensor");
  m.def("sample_backward(Tensor texture, Tensor uv, Tensor grad, int kind, int wrap_u, int wrap_v, float border, "
        "bool need_texture, bool need_uv) -> (Tensor?, Tensor?)");
  m.def("raster(Tensor pos, Tensor faces, int H, int W, bool cull, int bits, Tensor floor_z, Tensor floor_id, "
        "bool count, int layers) -> (Tensor, Tensor)");
  m.def("raster_fragments(Tensor pos, Tensor faces, Tensor tri_id, bool packed, int offset, bool derivatives) "
        "-> Tensor[]");
  m.def("raster_fused(Tensor pos, Tensor faces, int H, int W, bool cull, int bits, bool derivatives, "
        "bool keep_depth, int layers) -> Tensor[]");
  m.def("raster_fragments_backward(Tensor pos, Tensor faces, Tensor tri_id, Tensor idx, Tensor?[] grads, "
        "bool packed) -> Tensor");
  m.def("cube_front(Tensor dirs, Tensor dx, Tensor dy, Tensor bias, float bias0, int S, int levels, float band) "
        "-> (Tensor, Tensor, Tensor)");
  m.def("cube_front_backward(Tensor dirs, Tensor dx, Tensor dy, Tensor bias, float bias0, int S, int levels, "
        "float band, Tensor guv, Tensor gD, bool need_derivs, bool need_bias) -> (Tensor, Tensor?, Tensor?, Tensor?)");
  m.def("cube_read(Tensor[] levels, Tensor[] ring_idx, Tensor[] ring_w, Tensor face, Tensor uv, Tensor D, "
        "bool nearest, bool d_grad) -> Tensor");
  m.def("cube_read_backward(Tensor[] levels, Tensor[] ring_idx, Tensor[] ring_w, Tensor face, Tensor uv, Tensor D, "
        "Tensor grad, bool nearest, bool d_grad, bool need_levels, bool need_uv, bool need_D) "
        "-> (Tensor[], Tensor?, Tensor?)");
  m.def("sat_forward(Tensor texture, Tensor pu, Tensor cu, Tensor pv, Tensor cv, bool jacobians, bool coef_grads) "
        "-> Tensor[]");
  m.def("sat_backward(Tensor texture, Tensor pu, Tensor cu, Tensor pv, Tensor cv, Tensor grad) -> Tensor");
  m.def("ripmap_build(Tensor texture, int n_u, int n_v, int[] wanted) -> Tensor?[]");
  m.def("ripmap_adjoint(Tensor(a!)[] grads, int n_u, int n_v, int H, int W) -> Tensor");
  m.def("ripmap_read(Tensor[] levels, int n_u, Tensor uv, Tensor Du, Tensor Dv, int wrap_u, int wrap_v, "
        "float border, bool d_grad) -> Tensor");
  m.def("ripmap_read_backward(Tensor[] levels, int n_u, Tensor uv, Tensor Du, Tensor Dv, Tensor grad, int wrap_u, "
        "int wrap_v, float border, bool d_grad, bool need_levels, bool need_uv, bool need_D) "
        "-> (Tensor[], Tensor?, Tensor?, Tensor?)");
}

STABLE_TORCH_LIBRARY_IMPL(difftex, CPU, m) {
  m.impl("taps_forward", TORCH_BOX(&taps_forward));
  m.impl("taps_backward", TORCH_BOX(&taps_backward));
  m.impl("stochastic_taps_forward", TORCH_BOX(&stochastic_taps_forward));
  m.impl("stochastic_taps_backward", TORCH_BOX(&stochastic_taps_backward));
  m.impl("probe_offsets", TORCH_BOX(&probe_offsets_op));
  m.impl("tap_front", TORCH_BOX(&tap_front));
  m.impl("box2", TORCH_BOX(&box2_op));
  m.impl("box2_adjoint", TORCH_BOX(&box2_adjoint_op));
  m.impl("ewa_forward", TORCH_BOX(&ewa_forward));
  m.impl("ewa_backward", TORCH_BOX(&ewa_backward_op));
  m.impl("sample_forward", TORCH_BOX(&sample_forward));
  m.impl("sample_backward", TORCH_BOX(&sample_backward_op));
  m.impl("raster", TORCH_BOX(&raster_op));
  m.impl("raster_fragments", TORCH_BOX(&raster_fragments_op));
  m.impl("raster_fused", TORCH_BOX(&raster_fused_op));
  m.impl("raster_fragments_backward", TORCH_BOX(&raster_fragments_backward_op));
  m.impl("cube_front", TORCH_BOX(&cube_front_op));
  m.impl("cube_front_backward", TORCH_BOX(&cube_front_backward_op));
  m.impl("cube_read", TORCH_BOX(&cube_read_op));
  m.impl("cube_read_backward", TORCH_BOX(&cube_read_backward_op));
  m.impl("sat_forward", TORCH_BOX(&sat_forward_op));
  m.impl("sat_backward", TORCH_BOX(&sat_backward_op));
  m.impl("ripmap_build", TORCH_BOX(&ripmap_build_op));
  m.impl("ripmap_adjoint", TORCH_BOX(&ripmap_adjoint_op));
  m.impl("ripmap_read", TORCH_BOX(&ripmap_read_op));
  m.impl("ripmap_read_backward", TORCH_BOX(&ripmap_read_backward_op));
}

// difftex._C: importing it loads this library (and so registers the operators above). It also holds what
// is not an operator: the SIMD switches the tests turn (no tensor argument to dispatch on) and the
// constants mirrored from Python (common.h names the Python side of each; the tests check they agree).
// Python's limited API only, so that one build serves every Python >= 3.9.
namespace {

PyObject* py_bool_switch(PyObject* arg, bool (*set)(bool)) {
  const int on = PyObject_IsTrue(arg);
  if (on < 0) return nullptr;
  return PyBool_FromLong(set(on != 0));
}

PyObject* py_set_simd(PyObject*, PyObject* arg) { return py_bool_switch(arg, &set_simd); }
PyObject* py_set_wide(PyObject*, PyObject* arg) { return py_bool_switch(arg, &set_wide); }
PyObject* py_set_stream(PyObject*, PyObject* arg) { return py_bool_switch(arg, &set_stream); }
PyObject* py_simd_available(PyObject*, PyObject*) { return PyBool_FromLong(simd_available()); }
PyObject* py_wide_available(PyObject*, PyObject*) { return PyBool_FromLong(wide_available()); }

PyMethodDef methods[] = {
    {"set_simd", py_set_simd, METH_O,
     "set_simd(enabled) -> bool: use the eight-point AVX2 paths for float32 reads (default on); returns the "
     "previous setting"},
    {"simd_available", py_simd_available, METH_NOARGS, "whether this CPU runs the eight-point AVX2 paths"},
    {"set_wide", py_set_wide, METH_O,
     "set_wide(enabled) -> bool: read float32 bilinear / bicubic forwards sixteen points at a time (AVX-512; "
     "default on where set_simd is); returns the previous setting"},
    {"wide_available", py_wide_available, METH_NOARGS, "whether this CPU runs the sixteen-point AVX-512 forward"},
    {"set_stream", py_set_stream, METH_O,
     "set_stream(enabled) -> bool: let the sixteen-point forward write outputs of 1 MB or more with non-temporal "
     "stores (same values; default on); returns the previous setting"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C",
                          "difftex's native CPU kernels (the operators are torch.ops.difftex.*)", -1, methods};

bool add(PyObject* m, const char* name, PyObject* value) {
  if (value == nullptr) return false;
  const int rc = PyModule_AddObject(m, name, value);  // steals value on success
  if (rc < 0) Py_DECREF(value);
  return rc == 0;
}

bool add_codes(PyObject* m, const char* name, std::initializer_list<std::pair<const char*, long>> items) {
  PyObject* d = PyDict_New();
  if (d == nullptr) return false;
  for (const auto& [key, value] : items) {
    PyObject* v = PyLong_FromLong(value);
    if (v == nullptr || PyDict_SetItemString(d, key, v) < 0) {
      Py_XDECREF(v);
      Py_DECREF(d);
      return false;
    }
    Py_DECREF(v);
  }
  return add(m, name, d);
}

}  // namespace

extern "C" PyMODINIT_FUNC PyInit__C(void) {
  PyObject* m = PyModule_Create(&module_def);
  if (m == nullptr) return nullptr;
  const bool ok = add(m, "INDEX_CAP", PyFloat_FromDouble(kTwo52)) && add(m, "FAR", PyFloat_FromDouble(kFar)) &&
                  add(m, "RATIO_TOL", PyFloat_FromDouble(kRatioTol)) &&
                  add(m, "MAX_LOG2", PyFloat_FromDouble(kMaxLog2)) &&
                  add(m, "MAX_RATIO", PyFloat_FromDouble(kMaxRatio)) &&
                  add(m, "LOG2_FLOOR", PyFloat_FromDouble(kLog2Floor)) && add(m, "ALPHA", PyFloat_FromDouble(kAlpha)) &&
                  add(m, "MAX_MINOR", PyFloat_FromDouble(kMaxMinor)) &&
                  add(m, "DIR_FLOOR", PyFloat_FromDouble(kDirFloor)) &&
                  add(m, "DIR_FLOOR_FLOAT32", PyFloat_FromDouble(kDirFloorFloat)) &&
                  add(m, "CUBIC_A", PyFloat_FromDouble(kCubicA)) && add(m, "FAR_UV", PyFloat_FromDouble(kFarUv)) &&
                  add_codes(m, "WRAP_CODES", {{"repeat", REPEAT}, {"clamp", CLAMP}, {"mirror", MIRROR},
                                              {"border", BORDER}}) &&
                  add_codes(m, "KIND_CODES", {{"nearest", 0}, {"linear", 1}, {"cubic", 2}});
  if (!ok) {
    Py_DECREF(m);
    return nullptr;
  }
  return m;
}
