// The Python module of the native CPU kernel (difftex/texture/native): the
// entry points of taps.cpp, front.cpp, box.cpp and ewa.cpp, their options
// (filled by keyword from Python), and the constants the kernel shares with
// the Python reference, exported so that tests/texture/native/test_native.py
// checks each against the Python constant it mirrors. The only translation
// unit that defines the module.
#include "boxes.h"
#include "common.h"
#include "cube.h"
#include "kernels.h"

#include <array>
#include <utility>

namespace py = pybind11;
using namespace difftex;

namespace {

void check_wrap(int64_t code, const char* name) {
  TORCH_CHECK(code >= REPEAT && code <= BORDER, "mip_read.ReadOptions: ", name, " must be a wrap code 0-3, got ",
              code);
}

// Binds a struct of four gradient flags, each a keyword argument (default
// false) and a read-only attribute.
template <typename T>
void bind_needs(py::module_& m, const char* name, const char* doc,
                const std::array<std::pair<const char*, bool T::*>, 4>& flags) {
  py::class_<T> c(m, name, doc);
  c.def(py::init([flags](bool a, bool b, bool d, bool e) {
          T t{};
          t.*flags[0].second = a;
          t.*flags[1].second = b;
          t.*flags[2].second = d;
          t.*flags[3].second = e;
          return t;
        }),
        py::kw_only(), py::arg(flags[0].first) = false, py::arg(flags[1].first) = false,
        py::arg(flags[2].first) = false, py::arg(flags[3].first) = false);
  for (const auto& [field, member] : flags) c.def_readonly(field, member);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  py::class_<ReadOptions>(m, "ReadOptions", "How a pyramid read treats the texture (all by keyword).")
      .def(py::init([](int64_t wrap_u, int64_t wrap_v, double border, bool nearest, bool d_grad) {
             check_wrap(wrap_u, "wrap_u");
             check_wrap(wrap_v, "wrap_v");
             return ReadOptions{wrap_u, wrap_v, border, nearest, d_grad};
           }),
           py::kw_only(), py::arg("wrap_u"), py::arg("wrap_v"), py::arg("border") = 0.0, py::arg("nearest") = false,
           py::arg("d_grad") = false)
      .def_readonly("wrap_u", &ReadOptions::wrap_u)
      .def_readonly("wrap_v", &ReadOptions::wrap_v)
      .def_readonly("border", &ReadOptions::border)
      .def_readonly("nearest", &ReadOptions::nearest)
      .def_readonly("d_grad", &ReadOptions::d_grad);
  bind_needs<TapNeeds>(m, "TapNeeds", "The gradients the taps' backward computes (all by keyword).",
                       {{{"levels", &TapNeeds::levels}, {"uv", &TapNeeds::uv}, {"D", &TapNeeds::D},
                         {"axis", &TapNeeds::axis}}});
  bind_needs<EwaNeeds>(m, "EwaNeeds", "The gradients the EWA backward computes (all by keyword).",
                       {{{"levels", &EwaNeeds::levels}, {"uv", &EwaNeeds::uv}, {"ellipse", &EwaNeeds::ellipse},
                         {"D", &EwaNeeds::D}}});

  m.def("forward", &forward, "mip pyramid read, forward", py::arg("levels"), py::arg("uv"), py::arg("D"),
        py::arg("axis"), py::arg("count"), py::arg("opts"));
  m.def("backward", &backward, "mip pyramid read, first-order backward", py::arg("levels"), py::arg("uv"),
        py::arg("D"), py::arg("axis"), py::arg("count"), py::arg("grad"), py::arg("opts"), py::arg("need"));
  m.def("ewa", &ewa, "EWA filter, forward", py::arg("levels"), py::arg("uv"), py::arg("sigma"), py::arg("minor"),
        py::arg("scale"), py::arg("D"), py::arg("full_h"), py::arg("full_w"), py::arg("opts"));
  m.def("ewa_backward", &ewa_backward, "EWA filter, first-order backward", py::arg("levels"), py::arg("uv"),
        py::arg("sigma"), py::arg("minor"), py::arg("scale"), py::arg("D"), py::arg("grad"), py::arg("full_h"),
        py::arg("full_w"), py::arg("opts"), py::arg("need"));
  m.def("box2", &box2, "2 x 2 box step of an even level", py::arg("x"));
  m.def("box2_adjoint", &box2_adjoint, "transpose of box2: fine + coarse / 4 on each 2 x 2 block (fine None: zeros)",
        py::arg("coarse"), py::arg("fine") = py::none());
  m.def("front", &front, "mip level (and anisotropic / auto tap axis and count), no gradient", py::arg("dx"),
        py::arg("dy"), py::arg("bias"), py::kw_only(), py::arg("bias0"), py::arg("height"), py::arg("width"),
        py::arg("levels"), py::arg("kind"), py::arg("max_aniso"), py::arg("tolerance"));
  m.def("raster", &raster, "rasterize's visibility pass (ids and float64 depth)", py::arg("pos"), py::arg("faces"),
        py::arg("H"), py::arg("W"), py::arg("cull"), py::arg("bits"), py::arg("floor_z"), py::arg("floor_id"),
        py::kw_only(), py::arg("count") = false, py::arg("layers") = 1);
  m.def("raster_fragments", &raster_fragments, "rasterize's differentiable pass, forward", py::arg("pos"),
        py::arg("faces"), py::arg("tri_id"), py::kw_only(), py::arg("packed") = false, py::arg("offset") = 0);
  m.def("raster_fragments_backward", &raster_fragments_backward, "rasterize's differentiable pass, backward",
        py::arg("pos"), py::arg("faces"), py::arg("tri_id"), py::arg("idx"), py::arg("grads"), py::arg("packed"));

  // The constants mirrored from Python (common.h names the Python side of each).
  m.attr("INDEX_CAP") = kTwo52;
  m.attr("FAR") = kFar;
  m.attr("RATIO_TOL") = kRatioTol;
  m.attr("MAX_LOG2") = kMaxLog2;
  m.attr("MAX_RATIO") = kMaxRatio;
  m.attr("LOG2_FLOOR") = kLog2Floor;
  m.attr("ALPHA") = kAlpha;
  m.attr("MAX_MINOR") = kMaxMinor;
  m.attr("DIR_FLOOR") = kDirFloor;
  m.attr("DIR_FLOOR_FLOAT32") = kDirFloorFloat;
  py::dict codes;
  codes["repeat"] = static_cast<int>(REPEAT);
  codes["clamp"] = static_cast<int>(CLAMP);
  codes["mirror"] = static_cast<int>(MIRROR);
  codes["border"] = static_cast<int>(BORDER);
  m.attr("WRAP_CODES") = codes;

  // single.cpp: the single-level reads.
  m.def("sample", &sample, "nearest / bilinear / bicubic read of one level, forward", py::arg("texture"),
        py::arg("uv"), py::arg("kind"), py::arg("opts"));
  m.def("sample_backward", &sample_backward, "nearest / bilinear / bicubic read of one level, first-order backward",
        py::arg("texture"), py::arg("uv"), py::arg("grad"), py::arg("kind"), py::arg("opts"), py::kw_only(),
        py::arg("need_texture"), py::arg("need_uv"));
  m.def("set_simd", &set_simd, "use the eight-point AVX2 paths for float32 reads (default on); returns the previous setting",
        py::arg("enabled"));
  m.def("simd_available", &simd_available, "whether this CPU runs the eight-point AVX2 paths");
  m.def("set_wide", &set_wide, "read float32 bilinear / bicubic forwards sixteen points at a time (AVX-512; default "
        "on where set_simd is); returns the previous setting", py::arg("enabled"));
  m.def("wide_available", &wide_available, "whether this CPU runs the sixteen-point AVX-512 forward");
  py::dict kinds;
  kinds["nearest"] = 0;
  kinds["linear"] = 1;
  kinds["cubic"] = 2;
  m.attr("KIND_CODES") = kinds;
  m.attr("CUBIC_A") = kCubicA;
  m.attr("FAR_UV") = kFarUv;

  // cube.cpp: the cube-map front end and read (envmap/cube.py's native path).
  m.def("cube_front", &cube_front, "cube-map face, face uv and edge-blended trilinear level, no graph",
        py::arg("dirs"), py::arg("dx"), py::arg("dy"), py::arg("bias"), py::kw_only(), py::arg("bias0"), py::arg("S"),
        py::arg("levels"), py::arg("band"));
  m.def("cube_front_backward", &cube_front_backward, "cube_front, first-order backward", py::arg("dirs"),
        py::arg("dx"), py::arg("dy"), py::arg("bias"), py::kw_only(), py::arg("bias0"), py::arg("S"),
        py::arg("levels"), py::arg("band"), py::arg("guv"), py::arg("gD"), py::arg("need_derivs"),
        py::arg("need_bias"));
  m.def("cube_read", &cube_read, "seamless bilinear-tap read of a cube pyramid, forward", py::arg("levels"),
        py::arg("ring_idx"), py::arg("ring_w"), py::arg("face"), py::arg("uv"), py::arg("D"), py::arg("nearest"),
        py::arg("d_grad"));
  m.def("cube_read_backward", &cube_read_backward, "cube_read, first-order backward", py::arg("levels"),
        py::arg("ring_idx"), py::arg("ring_w"), py::arg("face"), py::arg("uv"), py::arg("D"), py::arg("grad"),
        py::arg("nearest"), py::arg("d_grad"), py::kw_only(), py::arg("need_levels"), py::arg("need_uv"),
        py::arg("need_D"));

  // sat.cpp: the summed-area table's box sums (filters/sat.py's native path).
  m.def("sat_forward", &sat_forward, "summed-area-table box sums, forward (and the per-point Jacobians)",
        py::arg("texture"), py::arg("pu"), py::arg("cu"), py::arg("pv"), py::arg("cv"), py::kw_only(),
        py::arg("jacobians") = false, py::arg("coef_grads") = true);
  m.def("sat_backward", &sat_backward, "summed-area-table box sums, the texture's gradient", py::arg("texture"),
        py::arg("pu"), py::arg("cu"), py::arg("pv"), py::arg("cv"), py::arg("grad"));
  // ripmap.cpp: the ripmap's build, read and adjoint (filters/ripmap.py's native path).
  m.def("ripmap_build", &ripmap_build, "ripmap levels (flat, j * n_u + i) of the wanted levels", py::arg("texture"),
        py::arg("n_u"), py::arg("n_v"), py::arg("wanted"));
  m.def("ripmap_adjoint", &ripmap_adjoint, "the texture's gradient from the ripmap levels' gradients",
        py::arg("grads"), py::arg("n_u"), py::arg("n_v"), py::arg("H"), py::arg("W"));
  m.def("ripmap_read", &ripmap_read, "ripmap filter read, forward", py::arg("levels"), py::arg("n_u"), py::arg("uv"),
        py::arg("Du"), py::arg("Dv"), py::arg("opts"));
  m.def("ripmap_read_backward", &ripmap_read_backward, "ripmap filter read, first-order backward", py::arg("levels"),
        py::arg("n_u"), py::arg("uv"), py::arg("Du"), py::arg("Dv"), py::arg("grad"), py::arg("opts"), py::kw_only(),
        py::arg("need_levels"), py::arg("need_uv"), py::arg("need_D"));
}
