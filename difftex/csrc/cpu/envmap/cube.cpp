// The cube-map passes on the CPU (difftex/envmap/cube.py, its native path;
// the torch path there stays the tested reference):
//
// * cube_front: per direction its face (OpenGL table 8.19, ties x over y
//   over z: directions.py _face_coords), face uv, and for the mip filters
//   the trilinear log2 length of the footprint in face texels, blended
//   within EDGE_BAND of an edge with the same length measured on the
//   neighbouring face (cube.py _edge_blend / _log2_length), so the level is
//   continuous across edges. Its backward recomputes the point and applies
//   the chain rule by hand (no graph, no temporaries per point).
// * cube_read: the bilinear taps of one or two levels (trilinear,
//   nearest-mip; bilinear is one level) read straight from the faces of
//   each level: a tap past a face edge reads the 1-texel gutter of
//   cube.py's atlas (_gutter_table: each gutter texel a weighted sum of up
//   to 3 texels, the cube folded across the edge, 3-texel means beyond the
//   corners), given here as one ring of slots around each face, so no
//   atlas is built. The backward scatters the level gradients by bands of
//   rows of the virtual atlas (bands.h): interior texels go straight to the
//   faces' gradients, gutter texels to a small per-slot buffer, folded onto
//   their source texels serially at the end (deterministic).
#include "cube.h"

#include "bands.h"
#include "common.h"

#include <cstring>

namespace difftex {

namespace {

// OpenGL 4.6 table 8.19 (mapping/common.py SC_AX ... MA_SGN).
constexpr int kScAx[6] = {2, 2, 0, 0, 0, 0};
constexpr double kScSg[6] = {-1, 1, 1, 1, 1, -1};
constexpr int kTcAx[6] = {1, 1, 2, 2, 1, 1};
constexpr double kTcSg[6] = {-1, -1, 1, -1, -1, -1};
constexpr int kMaAx[6] = {0, 0, 1, 1, 2, 2};
constexpr double kMaSg[6] = {1, -1, 1, -1, 1, -1};
// The floor of m_a by the inputs' dtype (cube.h; mapping/common.py dir_floor). A direction whose m_a on its
// own face is below it reads as the zero vector's face centre, with a point footprint and no gradient (the
// torch path's m_a = inf); a neighbouring face's m_a is clamped to it (cube.py _face_derivs).
template <bool kFloat> constexpr double eps_of() { return kFloat ? kDirFloorFloat : kDirFloor; }
constexpr double kLn2 = 0.69314718055994530942;

// log2 of a finite x > 0, faster than std::log2 here: the exponent from the bits, and the mantissa m in
// [sqrt(1/2), sqrt(2)) by the atanh series of t = (m - 1) / (m + 1), |t| < 0.1716, evaluated by Estrin's
// scheme (a short dependency chain: the front end is latency-bound). kFloat (float32 inputs): to t^9,
// absolute error below 1e-8 (the torch path computes in float32); else to t^19, below 1e-16.
template <bool kFloat>
DT_INLINE double log2_fast(double x) {
  if (!(x > 1e-300 && x < 1e300)) return std::log2(x);
  uint64_t bits;
  std::memcpy(&bits, &x, sizeof bits);
  const int64_t e = static_cast<int64_t>((bits >> 52) & 0x7ff) - 1023;
  bits = (bits & 0x000fffffffffffffULL) | 0x3ff0000000000000ULL;
  double m;
  std::memcpy(&m, &bits, sizeof m);
  const bool high = m > 1.4142135623730951;
  m = high ? 0.5 * m : m;
  const double t = (m - 1.0) / (m + 1.0), z = t * t, z2 = z * z, z4 = z2 * z2;
  double p;
  if (kFloat) {
    p = (1.0 + z * (1.0 / 3)) + z2 * ((1.0 / 5) + z * (1.0 / 7)) + z4 * (1.0 / 9);
  } else {
    const double z8 = z4 * z4;
    const double q0 = 1.0 + z * (1.0 / 3), q1 = 1.0 / 5 + z * (1.0 / 7), q2 = 1.0 / 9 + z * (1.0 / 11);
    const double q3 = 1.0 / 13 + z * (1.0 / 15), q4 = 1.0 / 17 + z * (1.0 / 19);
    p = (q0 + z2 * q1) + z4 * (q2 + z2 * q3) + z8 * q4;
  }
  return static_cast<double>(e + (high ? 1 : 0)) + (2.0 / kLn2) * t * p;
}

DT_INLINE int face_of(const double* d) {
  const double ax = std::abs(d[0]), ay = std::abs(d[1]), az = std::abs(d[2]);
  const bool isx = ax >= ay && ax >= az, isy = !isx && ay >= az;
  if (isx) return d[0] < 0 ? 1 : 0;
  if (isy) return d[1] < 0 ? 3 : 2;
  return d[2] < 0 ? 5 : 4;
}

// Gradients w.r.t. the face frame (s_c, t_c, m_a) scattered back to xyz.
DT_INLINE void to_xyz(int f, double g1, double g2, double g3, double* out) {
  out[kScAx[f]] += kScSg[f] * g1;
  out[kTcAx[f]] += kTcSg[f] * g2;
  out[kMaAx[f]] += kMaSg[f] * g3;
}

// log2 of the trilinear length (lod.py log2_length: max of the two derivative lengths, in texels; NaN or 0
// -> -FAR, inf -> +FAR, no gradient there) of the footprint (x, y) of direction d projected on face f
// (not necessarily d's own: m_a floored at dir_floor as cube.py _face_derivs), with what its gradient needs.
struct Measure {
  int f;
  bool live;  // a finite, non-zero length (else m is +-FAR, constant)
  double p1, p2, p3, p3r, i2, x1, x2, x3, y1, y2, y3, ux, vx, uy, vy, qx, qy, q, m;
};

template <bool kFloat>
DT_INLINE void measure(int f, bool own, const double* d, const double* x, const double* y, double S2, Measure* s) {
  s->f = f;
  s->p1 = kScSg[f] * d[kScAx[f]];
  s->p2 = kTcSg[f] * d[kTcAx[f]];
  s->p3r = kMaSg[f] * d[kMaAx[f]];
  s->p3 = s->p3r < eps_of<kFloat>() ? eps_of<kFloat>() : s->p3r;
  if (own && s->p3r < eps_of<kFloat>()) {  // the own face below the floor: a point (level 0)
    s->i2 = s->x1 = s->x2 = s->x3 = s->y1 = s->y2 = s->y3 = s->ux = s->vx = s->uy = s->vy = 0;
    s->qx = s->qy = s->q = 0;
    s->live = false;
    s->m = -kFar;
    return;
  }
  s->i2 = 1.0 / (s->p3 * s->p3);
  s->x1 = kScSg[f] * x[kScAx[f]], s->x2 = kTcSg[f] * x[kTcAx[f]], s->x3 = kMaSg[f] * x[kMaAx[f]];
  s->y1 = kScSg[f] * y[kScAx[f]], s->y2 = kTcSg[f] * y[kTcAx[f]], s->y3 = kMaSg[f] * y[kMaAx[f]];
  // d(face uv) = 0.5 (d s_c m_a - s_c d m_a) / m_a^2, per derivative.
  s->ux = 0.5 * (s->x1 * s->p3 - s->p1 * s->x3) * s->i2, s->vx = 0.5 * (s->x2 * s->p3 - s->p2 * s->x3) * s->i2;
  s->uy = 0.5 * (s->y1 * s->p3 - s->p1 * s->y3) * s->i2, s->vy = 0.5 * (s->y2 * s->p3 - s->p2 * s->y3) * s->i2;
  s->qx = s->ux * s->ux + s->vx * s->vx;
  s->qy = s->uy * s->uy + s->vy * s->vy;
  s->q = (std::isnan(s->qx) || std::isnan(s->qy)) ? std::numeric_limits<double>::quiet_NaN() : std::max(s->qx, s->qy);
  const double len2 = s->q * S2;
  s->live = len2 > 0 && len2 < std::numeric_limits<double>::infinity();
  s->m = s->live ? 0.5 * log2_fast<kFloat>(len2) : (len2 > 0 ? kFar : -kFar);
}

// Adds gm * d(measure)/d(d, x, y) to gd, gx, gy.
DT_INLINE void measure_grad(const Measure& s, double gm, double* gd, double* gx, double* gy) {
  if (!s.live || gm == 0) return;
  const double G = gm * 0.5 / (s.q * kLn2);
  // torch.maximum's backward: the larger one, half each at a tie.
  const double lx = s.qx > s.qy ? 1.0 : (s.qx == s.qy ? 0.5 : 0.0), ly = 1.0 - lx;
  double g1 = 0, g2 = 0, g3 = 0;
  auto chain = [&](double lam, double u, double v, double w1, double w2, double w3, double* out) {
    if (lam == 0) return;
    const double a = G * lam * 2 * u, b = G * lam * 2 * v;  // d/du, d/dv
    to_xyz(s.f, a * 0.5 / s.p3, b * 0.5 / s.p3, -(a * s.p1 + b * s.p2) * 0.5 * s.i2, out);
    g1 += a * (-0.5 * w3 * s.i2);
    g2 += b * (-0.5 * w3 * s.i2);
    g3 += a * (0.5 * w1 * s.i2 - 2 * u / s.p3) + b * (0.5 * w2 * s.i2 - 2 * v / s.p3);
  };
  chain(lx, s.ux, s.vx, s.x1, s.x2, s.x3, gx);
  chain(ly, s.uy, s.vy, s.y1, s.y2, s.y3, gy);
  if (s.p3r < s.p3) g3 = 0;  // clamp_min
  to_xyz(s.f, g1, g2, g3, gd);
}

// lod.py level: D = clamp(nan_to_num(l + b), 0, top), derivative 1 where 0 < l + b <= top.
DT_INLINE double level_of(double x, double top, bool* inside) {
  if (std::isnan(x)) x = 0;
  *inside = x > 0 && x <= top;
  return x < 0 ? 0 : (x > top ? top : x);
}

// One direction's front end: face, uv and (x, y given) log2 L. kGrad: recomputes it and adds the gradients
// of guv and gD (through D = level(l + bias), the level's slope known only here) to gd, gx, gy, and
// returns the bias's; the forward returns 0.
template <bool kGrad, bool kFloat>
DT_INLINE double front_point(const double* d, const double* x, const double* y, double S2, double band,
                             int8_t* face, double* uv, double* l, const double* guv, double gD, double bias,
                             double top, double* gd, double* gx, double* gy) {
  const int f = face_of(d);
  const double p1 = kScSg[f] * d[kScAx[f]], p2 = kTcSg[f] * d[kTcAx[f]], p3r = kMaSg[f] * d[kMaAx[f]];
  const double p3 = p3r < eps_of<kFloat>() ? std::numeric_limits<double>::infinity() : p3r;
  const double a = p1 / p3, b = p2 / p3;
  if (!kGrad) {
    *face = static_cast<int8_t>(f);
    uv[0] = 0.5 * (a + 1.0);
    uv[1] = 0.5 * (b + 1.0);
  }
  double ga = kGrad ? 0.5 * guv[0] : 0.0, gb = kGrad ? 0.5 * guv[1] : 0.0, gl = 0.0;
  if (x != nullptr && (!kGrad || gD != 0)) {
    Measure own, nb[2];
    measure<kFloat>(f, true, d, x, y, S2, &own);
    double num = own.m, den = 1.0, w[2] = {0, 0};
    const double c[2] = {a, b};
    for (int axis = 0; axis < 2; ++axis) {
      const double raw = 1.0 - (1.0 - std::abs(c[axis])) / band;
      w[axis] = raw < 0 ? 0.0 : (raw > 1 ? 1.0 : raw);
      if (!(w[axis] > 0)) continue;
      const int ax = axis == 0 ? kScAx[f] : kTcAx[f];
      const double sg = axis == 0 ? kScSg[f] : kTcSg[f];
      measure<kFloat>(2 * ax + (c[axis] * sg < 0 ? 1 : 0), false, d, x, y, S2, &nb[axis]);
      num += w[axis] * nb[axis].m;
      den += w[axis];
    }
    if (!kGrad) {
      *l = num / den;
    } else {
      bool inside;
      // The length rounded to the inputs' dtype before the bias is added, as the torch path does.
      level_of(kFloat ? static_cast<double>(static_cast<float>(num / den) + static_cast<float>(bias)) : num / den + bias,
               top, &inside);
      gl = inside ? gD : 0.0;
      if (gl != 0) {
        const double gnum = gl / den, gden = -gl * num / (den * den);
        measure_grad(own, gnum, gd, gx, gy);
        for (int axis = 0; axis < 2; ++axis) {
          if (!(w[axis] > 0)) continue;
          measure_grad(nb[axis], gnum * w[axis], gd, gx, gy);
          const double raw = 1.0 - (1.0 - std::abs(c[axis])) / band;
          if (raw <= 1.0) {  // clamp passes its gradient at the ends
            const double gc = (gnum * nb[axis].m + gden) * (c[axis] > 0 ? 1.0 : (c[axis] < 0 ? -1.0 : 0.0)) / band;
            (axis == 0 ? ga : gb) += gc;
          }
        }
      }
    }
  }
  if (kGrad) {
    // a = s_c / m_a, b = t_c / m_a.
    const double g3 = p3r < p3 ? 0.0 : -(ga * p1 + gb * p2) / (p3 * p3);
    to_xyz(f, ga / p3, gb / p3, g3, gd);
  }
  return gl;
}

void check_front(const Tensor& dirs, const Tensor& dx, const Tensor& dy,
                 const Tensor& bias) {
  DT_CHECK(dirs.dim() == 2 && dirs.size(1) == 3 && dirs.is_contiguous() && dirs.is_cpu(),
              "cube_front: dirs must be contiguous CPU [M, 3]");
  for (const auto* t : {&dx, &dy})
    DT_CHECK(t->numel() == 0 || (t->sizes() == dirs.sizes() && t->is_contiguous() &&
                                    t->scalar_type() == dirs.scalar_type()),
                "cube_front: dx, dy must be contiguous [M, 3] like dirs (or both empty)");
  DT_CHECK((dx.numel() == 0) == (dy.numel() == 0), "cube_front: give dx and dy together");
  DT_CHECK(bias.numel() == 0 || (bias.dim() == 1 && bias.size(0) == dirs.size(0) && bias.is_contiguous() &&
                                    bias.scalar_type() == dirs.scalar_type()),
              "cube_front: bias must be contiguous [M] of dirs' dtype (or empty)");
}

// -1 for the zero vector, -2 for a non-finite one (cube.py: 0 and NaN in their pixels, no gradient), else 0.
DT_INLINE int bad_direction(const double* d) {
  if (!std::isfinite(d[0]) || !std::isfinite(d[1]) || !std::isfinite(d[2])) return -2;
  return d[0] == 0 && d[1] == 0 && d[2] == 0 ? -1 : 0;
}

// Face and uv of a direction in selects, no table lookups (the bilinear front end, which is nothing else;
// measured about 15% faster than front_point's lookups): directions.py _face_coords, (s_c, t_c, m_a) =
// (-g z, -y, g x) on +-X, (x, g z, g y) on +-Y, (g x, -y, g z) on +-Z, g the sign of the major component;
// -1 / -2 for a zero / non-finite direction (uv 0.5).
template <typename scalar_t>
DT_INLINE int face_uv(const scalar_t* p, double* uv) {
  const double x = p[0], y = p[1], z = p[2];
  const double ax = std::abs(x), ay = std::abs(y), az = std::abs(z);
  uv[0] = uv[1] = 0.5;
  if (!std::isfinite(x * 0.0 + y * 0.0 + z * 0.0)) return -2;
  if (ax + ay + az == 0) return -1;
  const bool isx = ax >= ay && ax >= az, isy = !isx && ay >= az;
  const double major = isx ? x : (isy ? y : z);
  const bool neg = major < 0;
  const double g = neg ? -1.0 : 1.0;
  const double sc = isx ? -g * z : (isy ? x : g * x), tc = isy ? g * z : -y;
  const double ma = g * major < eps_of<std::is_same_v<scalar_t, float>>() ? std::numeric_limits<double>::infinity()
                                                                          : g * major;
  const double r = 1.0 / ma;
  uv[0] = 0.5 * (sc * r + 1.0);
  uv[1] = 0.5 * (tc * r + 1.0);
  return (isx ? 0 : (isy ? 2 : 4)) + (neg ? 1 : 0);
}

// Point e of cube_front (px, py null: no level): its face, uv and (D not null) level, in the inputs' dtype.
template <typename scalar_t>
DT_INLINE void front_one(int64_t e, const scalar_t* pd, const scalar_t* px, const scalar_t* py, const scalar_t* pb,
                         double bias0, double S2, double band, double top, int8_t* face, scalar_t* uv, scalar_t* D) {
  const bool derivs = px != nullptr;
  if (!derivs) {
    double u[2];
    *face = static_cast<int8_t>(face_uv(pd + 3 * e, u));
    uv[0] = static_cast<scalar_t>(u[0]);
    uv[1] = static_cast<scalar_t>(u[1]);
    return;
  }
  double d[3], x[3], y[3], u[2] = {0.5, 0.5}, len = 0;
  for (int i = 0; i < 3; ++i) {
    d[i] = pd[3 * e + i];
    if (derivs) x[i] = px[3 * e + i], y[i] = py[3 * e + i];
  }
  const int bad = bad_direction(d);
  if (bad)
    *face = static_cast<int8_t>(bad);
  else
    front_point<false, std::is_same<scalar_t, float>::value>(d, derivs ? x : nullptr, derivs ? y : nullptr, S2, band,
                                                              face, u, &len, nullptr, 0, 0, top, nullptr, nullptr,
                                                              nullptr);
  uv[0] = static_cast<scalar_t>(u[0]);
  uv[1] = static_cast<scalar_t>(u[1]);
  if (D != nullptr) {
    bool inside;
    // The length in the tensor's dtype first, as the torch path adds it to the bias.
    *D = bad ? scalar_t(0)
             : static_cast<scalar_t>(level_of(
                   static_cast<double>(static_cast<scalar_t>(len) + (pb ? pb[e] : static_cast<scalar_t>(bias0))), top,
                   &inside));
  }
}

}  // namespace

std::tuple<Tensor, Tensor, Tensor> cube_front(Tensor dirs, Tensor dx,
                                                                   Tensor dy, Tensor bias,
                                                                   double bias0, int64_t S, int64_t levels,
                                                                   double band) {
  check_front(dirs, dx, dy, bias);
  const int64_t M = dirs.size(0);
  const bool derivs = dx.numel() > 0;
  auto face = empty({M}, options_of(dirs).dtype(kInt8));
  auto uv = empty({M, 2}, options_of(dirs));
  auto D = derivs ? empty({M}, options_of(dirs)) : empty({0}, options_of(dirs));
  const double S2 = static_cast<double>(S) * static_cast<double>(S), top = static_cast<double>(levels - 1);
  DT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "cube_front", [&] {
    const scalar_t *pd = dirs.mutable_data_ptr<scalar_t>(), *px = derivs ? dx.mutable_data_ptr<scalar_t>() : nullptr,
                   *py = derivs ? dy.mutable_data_ptr<scalar_t>() : nullptr,
                   *pb = bias.numel() ? bias.mutable_data_ptr<scalar_t>() : nullptr;
    int8_t* pf = face.mutable_data_ptr<int8_t>();
    scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *pD = derivs ? D.mutable_data_ptr<scalar_t>() : nullptr;
    parallel_for(0, M, 2048, [&](int64_t lo, int64_t hi) {
      for (int64_t e = lo; e < hi; ++e)
        front_one(e, pd, px, py, pb, bias0, S2, band, top, pf + e, puv + 2 * e, derivs ? pD + e : nullptr);
    });
  });
  return {face, uv, D};
}

std::tuple<Tensor, Tensor, Tensor, Tensor> cube_front_backward(
    Tensor dirs, Tensor dx, Tensor dy, Tensor bias, double bias0, int64_t S,
    int64_t levels, double band, Tensor guv, Tensor gD, bool need_derivs, bool need_bias) {
  check_front(dirs, dx, dy, bias);
  const int64_t M = dirs.size(0);
  const bool derivs = dx.numel() > 0, has_gD = gD.numel() > 0 && derivs;
  guv = contig(guv);
  gD = contig(gD);
  DT_CHECK(guv.dim() == 2 && guv.size(0) == M && guv.size(1) == 2 && guv.scalar_type() == dirs.scalar_type(),
              "cube_front_backward: guv must be [M, 2] of dirs' dtype");
  DT_CHECK(gD.numel() == 0 || (gD.dim() == 1 && gD.size(0) == M && gD.scalar_type() == dirs.scalar_type()),
              "cube_front_backward: gD must be [M] of dirs' dtype (or empty)");
  need_derivs = need_derivs && has_gD;
  need_bias = need_bias && has_gD;
  auto gd = empty({M, 3}, options_of(dirs));
  Tensor gx = need_derivs ? empty({M, 3}, options_of(dirs)) : Tensor();
  Tensor gy = need_derivs ? empty({M, 3}, options_of(dirs)) : Tensor();
  Tensor gb = need_bias ? empty({M}, options_of(dirs)) : Tensor();
  const double S2 = static_cast<double>(S) * static_cast<double>(S), top = static_cast<double>(levels - 1);
  DT_DISPATCH_FLOATING_TYPES(dirs.scalar_type(), "cube_front_backward", [&] {
    const scalar_t *pd = dirs.mutable_data_ptr<scalar_t>(), *px = derivs ? dx.mutable_data_ptr<scalar_t>() : nullptr,
                   *py = derivs ? dy.mutable_data_ptr<scalar_t>() : nullptr, *pguv = guv.mutable_data_ptr<scalar_t>(),
                   *pgD = has_gD ? gD.mutable_data_ptr<scalar_t>() : nullptr,
                   *pb = bias.numel() ? bias.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t *pgd = gd.mutable_data_ptr<scalar_t>(), *pgx = need_derivs ? gx.mutable_data_ptr<scalar_t>() : nullptr,
             *pgy = need_derivs ? gy.mutable_data_ptr<scalar_t>() : nullptr, *pgb = need_bias ? gb.mutable_data_ptr<scalar_t>() : nullptr;
    parallel_for(0, M, 2048, [&](int64_t lo, int64_t hi) {
      for (int64_t e = lo; e < hi; ++e) {
        double d[3], x[3], y[3], g[3] = {0, 0, 0}, hx[3] = {0, 0, 0}, hy[3] = {0, 0, 0}, gl = 0;
        for (int i = 0; i < 3; ++i) {
          d[i] = pd[3 * e + i];
          if (derivs) x[i] = px[3 * e + i], y[i] = py[3 * e + i];
        }
        const bool bad = bad_direction(d) != 0;
        if (!bad) {
          const double gu[2] = {static_cast<double>(pguv[2 * e]), static_cast<double>(pguv[2 * e + 1])};
          const double b = static_cast<double>(pb ? pb[e] : static_cast<scalar_t>(bias0));
          gl = front_point<true, std::is_same<scalar_t, float>::value>(
              d, has_gD ? x : nullptr, has_gD ? y : nullptr, S2, band, nullptr, nullptr, nullptr, gu,
              has_gD ? static_cast<double>(pgD[e]) : 0.0, b, top, g, hx, hy);
        }
        for (int i = 0; i < 3; ++i) {
          pgd[3 * e + i] = static_cast<scalar_t>(g[i]);
          if (need_derivs) pgx[3 * e + i] = static_cast<scalar_t>(hx[i]), pgy[3 * e + i] = static_cast<scalar_t>(hy[i]);
        }
        if (need_bias) pgb[e] = static_cast<scalar_t>(gl);
      }
    });
  });
  return {gd, gx, gy, gb};
}

// ---------------------------------------------------------------- the read

namespace {

struct CubeLevel {
  int64_t n, P, plane, fstride, ring;  // ring: slots per face, 4 P - 4
  const int64_t* ri;
  const double* rw;
};

// Slot of padded texel (y, x) on the ring of a face of P x P padded texels (cube.py _ring_tables).
DT_INLINE int64_t ring_slot(int64_t y, int64_t x, int64_t P) {
  if (y == 0) return x;
  if (y == P - 1) return P + x;
  if (x == 0) return 2 * P + (y - 1);
  return 2 * P + (P - 2) + (y - 1);
}

// The (up to 3) texels that padded texel (f, y, x) of a level reads: offsets in [6, C, n, n] (channel 0),
// weights, and its ring slot (-1 inside the face).
struct Source {
  int k;
  int64_t slot;
  int64_t a[3];
  double w[3];
};

DT_INLINE void source_of(const CubeLevel& L, int64_t f, int64_t y, int64_t x, Source* s) {
  if (y >= 1 && y <= L.n && x >= 1 && x <= L.n) {
    s->k = 1;
    s->slot = -1;
    s->a[0] = f * L.fstride + (y - 1) * L.n + (x - 1);
    s->w[0] = 1.0;
    return;
  }
  const int64_t r = f * L.ring + ring_slot(y, x, L.P);
  s->k = 3;
  s->slot = r;
  for (int q = 0; q < 3; ++q) {
    const int64_t idx = L.ri[3 * r + q], fi = idx / L.plane;
    s->a[q] = fi * L.fstride + (idx - fi * L.plane);
    s->w[q] = L.rw[3 * r + q];
  }
}

// floor of a padded texel coordinate, x >= 0 for every face uv in [0, 1]: a truncation, no branch (the
// fraction is random from point to point; common.h floor_capped's compare mispredicts, as single.cpp
// measured). Anything else (never for a face uv) takes floor_capped.
DT_INLINE double floor_pos(double x) {
  return x >= 0 && x < 1e15 ? static_cast<double>(static_cast<int64_t>(x)) : floor_capped(x);
}

// common.h reads_of, the same levels and weights, for the levels D >= 0 that lod.py level gives (others
// go to reads_of): its floor a truncation (floor_pos), as D's fraction varies from point to point and
// floor_capped's compare mispredicts.
DT_INLINE Reads cube_reads(double d, int64_t K, bool nearest, bool d_grad) {
  if (!(d >= 0 && d < 1e15)) return reads_of(d, K, nearest, d_grad);
  const double top = static_cast<double>(K - 1);
  Reads r;
  if (nearest) {
    const double k = std::min(floor_pos(d + 0.5), top);
    r.n = 1; r.k[0] = static_cast<int64_t>(k); r.wt[0] = 1.0; r.dwt[0] = 0.0;
    return r;
  }
  const double k0 = std::min(floor_pos(d), top), t = d - k0;
  r.k[0] = static_cast<int64_t>(k0);
  if (k0 < top && t > 0) {
    r.n = 2; r.wt[0] = 1.0 - t; r.dwt[0] = -1.0;
    r.k[1] = r.k[0] + 1; r.wt[1] = t; r.dwt[1] = 1.0;
  } else if (d_grad && k0 > 0) {
    r.n = 2; r.wt[0] = 1.0; r.dwt[0] = 1.0;
    r.k[1] = r.k[0] - 1; r.wt[1] = 0.0; r.dwt[1] = -1.0;
  } else {
    r.n = 1; r.wt[0] = 1.0; r.dwt[0] = 0.0;
  }
  return r;
}

// The level of point e (D empty: 0, one level).
template <typename scalar_t>
DT_INLINE double level_at(const scalar_t* pd, int64_t e) { return pd == nullptr ? 0.0 : static_cast<double>(pd[e]); }

DT_INLINE int64_t clamp_i(double v, int64_t hi) {
  return v < 0 ? 0 : (v > static_cast<double>(hi) ? hi : static_cast<int64_t>(v));
}

// One bilinear read of level L at face uv: the four padded texels and the fractions.
struct Tap {
  Source s[4];
  double fx, fy;
  int64_t row0;  // padded row of the upper taps
};

DT_INLINE void tap_of(const CubeLevel& L, int64_t f, double u, double v, Tap* t) {
  const double x = u * static_cast<double>(L.n) + 0.5, y = v * static_cast<double>(L.n) + 0.5;
  const double x0 = floor_pos(x), y0 = floor_pos(y);
  t->fx = x - x0;
  t->fy = y - y0;
  const int64_t c0 = clamp_i(x0, L.P - 1), c1 = clamp_i(x0 + 1, L.P - 1);
  const int64_t r0 = clamp_i(y0, L.P - 1), r1 = clamp_i(y0 + 1, L.P - 1);
  t->row0 = r0;
  source_of(L, f, r0, c0, &t->s[0]);
  source_of(L, f, r0, c1, &t->s[1]);
  source_of(L, f, r1, c0, &t->s[2]);
  source_of(L, f, r1, c1, &t->s[3]);
}

// The fast path of a read: where all four taps lie inside the face (most points), their offset (the
// upper left one, channel 0) and the fractions; false where a tap reads the gutter (then tap_of).
DT_INLINE bool inner_tap(const CubeLevel& L, int64_t f, double u, double v, int64_t* base, double* fx, double* fy) {
  const double n = static_cast<double>(L.n);
  const double x = u * n + 0.5, y = v * n + 0.5;
  const double x0 = floor_pos(x), y0 = floor_pos(y);
  *fx = x - x0;
  *fy = y - y0;
  if (!(x0 >= 1 && x0 + 1 <= n && y0 >= 1 && y0 + 1 <= n)) return false;
  *base = f * L.fstride + (static_cast<int64_t>(y0) - 1) * L.n + (static_cast<int64_t>(x0) - 1);
  return true;
}

template <typename scalar_t>
DT_INLINE scalar_t fetch(const Source& s, const scalar_t* p) {
  if (s.k == 1) return p[s.a[0]];
  return static_cast<scalar_t>(s.w[0]) * p[s.a[0]] + static_cast<scalar_t>(s.w[1]) * p[s.a[1]] +
         static_cast<scalar_t>(s.w[2]) * p[s.a[2]];
}

std::vector<CubeLevel> level_tables(const std::vector<Tensor>& levels, const std::vector<Tensor>& ri,
                                    const std::vector<Tensor>& rw, ScalarType dtype);

std::vector<CubeLevel> cube_levels(const std::vector<Tensor>& levels, const std::vector<Tensor>& ri,
                                   const std::vector<Tensor>& rw, const Tensor& face,
                                   const Tensor& uv, const Tensor& D) {
  const int64_t M = uv.size(0);
  DT_CHECK(uv.dim() == 2 && uv.size(1) == 2 && uv.is_contiguous(), "cube_read: uv must be contiguous [M, 2]");
  DT_CHECK(face.dim() == 1 && face.size(0) == M && face.scalar_type() == kInt8 && face.is_contiguous(),
              "cube_read: face must be contiguous int8 [M]");
  DT_CHECK(D.numel() == 0 || (D.dim() == 1 && D.size(0) == M && D.scalar_type() == uv.scalar_type() &&
                                 D.is_contiguous()),
              "cube_read: D must be contiguous [M] of uv's dtype (or empty: level 0)");
  return level_tables(levels, ri, rw, uv.scalar_type());
}

std::vector<CubeLevel> level_tables(const std::vector<Tensor>& levels, const std::vector<Tensor>& ri,
                                    const std::vector<Tensor>& rw, ScalarType dtype) {
  DT_CHECK(!levels.empty() && levels.size() == ri.size() && levels.size() == rw.size(),
              "cube_read: one ring table per level");
  const int64_t C = levels[0].size(1);
  std::vector<CubeLevel> out;
  for (size_t k = 0; k < levels.size(); ++k) {
    const auto& t = levels[k];
    DT_CHECK(t.dim() == 4 && t.size(0) == 6 && t.size(1) == C && t.size(2) == t.size(3) && t.is_contiguous() &&
                    t.scalar_type() == dtype && t.is_cpu(),
                "cube_read: levels must be contiguous CPU [6, C, n, n] of uv's dtype");
    const int64_t n = t.size(2), P = n + 2;
    DT_CHECK(ri[k].dim() == 2 && ri[k].size(0) == 6 * (4 * P - 4) && ri[k].size(1) == 3 &&
                    ri[k].scalar_type() == kInt64 && ri[k].is_contiguous() && rw[k].sizes() == ri[k].sizes() &&
                    rw[k].scalar_type() == kFloat64 && rw[k].is_contiguous(),
                "cube_read: ring tables must be contiguous [6 (4 P - 4), 3] int64 / float64");
    out.push_back({n, P, n * n, C * n * n, 4 * P - 4, ri[k].mutable_data_ptr<int64_t>(), rw[k].mutable_data_ptr<double>()});
  }
  return out;
}

// Texel rows are prefetched kAhead points ahead (the faces are larger than the caches; measured on the
// CPU: about a third off the read), for the face gradients too in the backward.
constexpr int64_t kAhead = 12;

// P: const scalar_t* (the levels, read) or scalar_t* (their gradients, written).
template <bool kWrite, typename P>
DT_INLINE void prefetch_point(const std::vector<CubeLevel>& L, const std::vector<P>& planes, int64_t C,
                              int64_t f, double u, double v, double D) {
  if (f < 0 || f > 5 || !std::isfinite(u) || !std::isfinite(v) || !std::isfinite(D)) return;
  const int64_t K = static_cast<int64_t>(L.size());
  const double kd = floor_pos(D);
  const int64_t k0 = kd < 0 ? 0 : (kd > static_cast<double>(K - 1) ? K - 1 : static_cast<int64_t>(kd));
  const int64_t k1 = D > kd && k0 + 1 < K ? k0 + 1 : k0;
  for (int64_t k = k0; k <= k1; ++k) {
    const CubeLevel& lv = L[k];
    if (planes[k] == nullptr) continue;
    const double n = static_cast<double>(lv.n);
    const int64_t x = clamp_i(u * n - 0.5, lv.n - 1), y = clamp_i(v * n - 0.5, lv.n - 1);
    const auto* p = planes[k] + f * lv.fstride + y * lv.n + x;
    for (int64_t c = 0; c < C; ++c) {
      DT_PREFETCH(p + c * lv.plane, kWrite);
      DT_PREFETCH(p + c * lv.plane + lv.n, kWrite);
    }
  }
}

// Point e's read, any taps (the gutter included): the general path of read_range.
template <typename scalar_t, int CC>
DT_INLINE void read_point(int64_t e, int64_t C, const std::vector<CubeLevel>& L,
                          const std::vector<const scalar_t*>& lp, int64_t f, double u, double v, const Reads& r,
                          scalar_t* po, int64_t M, scalar_t* acc) {
  for (int64_t c = 0; c < C; ++c) acc[c] = 0;
  for (int j = 0; j < r.n; ++j) {
    const CubeLevel& lv = L[r.k[j]];
    const scalar_t* p = lp[r.k[j]];
    const double wl = r.wt[j];
    Tap t;
    tap_of(lv, f, u, v, &t);
    const scalar_t w[4] = {static_cast<scalar_t>(wl * (1 - t.fx) * (1 - t.fy)),
                           static_cast<scalar_t>(wl * t.fx * (1 - t.fy)),
                           static_cast<scalar_t>(wl * (1 - t.fx) * t.fy), static_cast<scalar_t>(wl * t.fx * t.fy)};
    for (int64_t c = 0; c < C; ++c) {
      const scalar_t* pp = p + c * lv.plane;
      acc[c] += w[0] * fetch(t.s[0], pp) + w[1] * fetch(t.s[1], pp) + w[2] * fetch(t.s[2], pp) +
                w[3] * fetch(t.s[3], pp);
    }
  }
  for (int64_t c = 0; c < C; ++c) po[c * M + e] = acc[c];
}

// The forward over points [lo, hi), in blocks (as single.cpp's): first every point's levels and taps (the
// fast path where all of them lie inside its face), then their texel rows prefetched for the whole block
// (the faces are larger than the caches: one point's loads after another's leave the loop waiting on
// memory), then the reads; a point with a tap in the gutter takes read_point.
template <typename scalar_t, int CC>
void read_range(int64_t lo, int64_t hi, int64_t Cdyn, const std::vector<CubeLevel>& L,
                const std::vector<const scalar_t*>& lp, const int8_t* pf, const scalar_t* puv, const scalar_t* pd,
                scalar_t* po, int64_t M, bool nearest, bool d_grad) {
  constexpr int kB = 64;
  const int64_t C = CC > 0 ? CC : Cdyn, K = static_cast<int64_t>(L.size());
  std::vector<scalar_t> heap(CC > 0 ? 0 : C);
  scalar_t stack[CC > 0 ? CC : 1];
  scalar_t* acc = CC > 0 ? stack : heap.data();
  int64_t base[2][kB];
  double wts[2][kB][4];
  int lev[2][kB], nl[kB];  // levels read; nl: their number on the fast path, 0 general, -1 no read
  for (int64_t s = lo; s < hi; s += kB) {
    const int cnt = static_cast<int>(std::min<int64_t>(kB, hi - s));
    for (int i = 0; i < cnt; ++i) {
      const int64_t e = s + i, f = pf[e];
      const double u = puv[2 * e], v = puv[2 * e + 1];
      if (!std::isfinite(u) || !std::isfinite(v) || f < 0 || f > 5) {
        nl[i] = -1;
        continue;
      }
      const Reads r = cube_reads(level_at(pd, e), K, nearest, d_grad);
      nl[i] = r.n;
      for (int j = 0; j < r.n; ++j) {
        double fx, fy;
        lev[j][i] = static_cast<int>(r.k[j]);
        if (!inner_tap(L[r.k[j]], f, u, v, &base[j][i], &fx, &fy)) {
          nl[i] = 0;
          break;
        }
        const double wl = r.wt[j];
        wts[j][i][0] = wl * (1 - fx) * (1 - fy);
        wts[j][i][1] = wl * fx * (1 - fy);
        wts[j][i][2] = wl * (1 - fx) * fy;
        wts[j][i][3] = wl * fx * fy;
      }
    }
    for (int i = 0; i < cnt; ++i)
      for (int j = 0; j < nl[i]; ++j) {
        const CubeLevel& lv = L[lev[j][i]];
        const scalar_t* p = lp[lev[j][i]] + base[j][i];
        for (int64_t c = 0; c < C; ++c) {
          DT_PREFETCH(p + c * lv.plane, false);
          DT_PREFETCH(p + c * lv.plane + lv.n, false);
        }
      }
    for (int i = 0; i < cnt; ++i) {
      const int64_t e = s + i, f = pf[e];
      if (nl[i] < 0) {
        // face -1: a zero direction (0); else NaN (cube_front's codes).
        const scalar_t fill = f == -1 ? scalar_t(0) : std::numeric_limits<scalar_t>::quiet_NaN();
        for (int64_t c = 0; c < C; ++c) po[c * M + e] = fill;
        continue;
      }
      if (nl[i] == 0) {
        read_point<scalar_t, CC>(e, C, L, lp, f, puv[2 * e], puv[2 * e + 1],
                                 cube_reads(level_at(pd, e), K, nearest, d_grad), po, M, acc);
        continue;
      }
      for (int64_t c = 0; c < C; ++c) acc[c] = 0;
      for (int j = 0; j < nl[i]; ++j) {
        const CubeLevel& lv = L[lev[j][i]];
        const int64_t n = lv.n;
        const scalar_t w0 = static_cast<scalar_t>(wts[j][i][0]), w1 = static_cast<scalar_t>(wts[j][i][1]),
                       w2 = static_cast<scalar_t>(wts[j][i][2]), w3 = static_cast<scalar_t>(wts[j][i][3]);
        const scalar_t* p = lp[lev[j][i]] + base[j][i];
        for (int64_t c = 0; c < C; ++c) {
          const scalar_t* pp = p + c * lv.plane;
          acc[c] += w0 * pp[0] + w1 * pp[1] + w2 * pp[n] + w3 * pp[n + 1];
        }
      }
      for (int64_t c = 0; c < C; ++c) po[c * M + e] = acc[c];
    }
  }
}

template <typename F>
void by_channels(int64_t C, F&& f) {
  switch (C) {
    case 1: f(std::integral_constant<int, 1>()); break;
    case 3: f(std::integral_constant<int, 3>()); break;
    case 4: f(std::integral_constant<int, 4>()); break;
    default: f(std::integral_constant<int, 0>());
  }
}

}  // namespace

Tensor cube_read(std::vector<Tensor> levels, std::vector<Tensor> ring_idx,
                        std::vector<Tensor> ring_w, Tensor face, Tensor uv, Tensor D,
                        bool nearest, bool d_grad) {
  auto L = cube_levels(levels, ring_idx, ring_w, face, uv, D);
  const int64_t C = levels[0].size(1), M = uv.size(0);
  auto out = empty({C, M}, options_of(uv));
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "cube_read", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.mutable_data_ptr<scalar_t>());
    const int8_t* pf = face.mutable_data_ptr<int8_t>();
    const scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *pd = D.numel() ? D.mutable_data_ptr<scalar_t>() : nullptr;
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
      by_channels(C, [&](auto cc) {
        read_range<scalar_t, decltype(cc)::value>(lo, hi, C, L, lp, pf, puv, pd, po, M, nearest, d_grad);
      });
    });
  });
  return out;
}

namespace {

// The bands of the level-gradient scatter are bands.h's ScaleBands, as in
// taps.cpp, over the rows of the virtual atlas of each level (6 faces of
// P_k padded rows, stacked): the same fractions of every level's height.
DT_INLINE int32_t cube_key(const ScaleBands& T, const std::vector<CubeLevel>& L, int64_t f, double u, double v,
                           const Reads& r) {
  if (!std::isfinite(u) || !std::isfinite(v) || f < 0 || f > 5) return -1;
  int64_t a[2], b[2], h[2];
  for (int j = 0; j < r.n; ++j) {
    const CubeLevel& lv = L[r.k[j]];
    const int64_t y0 = clamp_i(floor_pos(v * static_cast<double>(lv.n) + 0.5), lv.P - 1);
    h[j] = 6 * lv.P;
    // A margin row on each side (as taps.cpp).
    a[j] = std::max<int64_t>(f * lv.P + y0 - 1, 0);
    b[j] = std::min<int64_t>(f * lv.P + y0 + 2, h[j] - 1);
  }
  int64_t nb = T.nb0;
  for (int64_t s = 0; s < T.scales; ++s, nb /= 2) {
    int64_t band = std::numeric_limits<int64_t>::max();
    for (int j = 0; j < r.n; ++j) band = std::min(band, a[j] * nb / h[j]);
    bool fits = true;
    for (int j = 0; j < r.n; ++j) fits = fits && (b[j] + 1) * nb <= (band + 2) * h[j];
    if (fits) return static_cast<int32_t>(T.offset[s] + band);
  }
  return static_cast<int32_t>(T.serial);
}

template <typename scalar_t>
struct CubeGrads {
  std::vector<scalar_t*> gp, gr;  // per level: the faces' gradient [6, C, n, n], the ring slots' [R, C]
  scalar_t *uv, *D;
};

template <typename scalar_t, int CC>
DT_INLINE void backward_point(int64_t e, int64_t Cdyn, const std::vector<CubeLevel>& L,
                              const std::vector<const scalar_t*>& lp, const int8_t* pf, const scalar_t* puv,
                              const scalar_t* pd, const scalar_t* pg, const CubeGrads<scalar_t>& out, int64_t M,
                              bool nearest, bool d_grad) {
  const int64_t C = CC > 0 ? CC : Cdyn, K = static_cast<int64_t>(L.size());
  std::vector<scalar_t> heap(CC > 0 ? 0 : C);
  scalar_t stack[CC > 0 ? CC : 1];
  scalar_t* g = CC > 0 ? stack : heap.data();
  const double u = puv[2 * e], v = puv[2 * e + 1];
  const int64_t f = pf[e];
  if (!std::isfinite(u) || !std::isfinite(v) || f < 0 || f > 5) return;
  bool any = false;
  for (int64_t c = 0; c < C; ++c) {
    g[c] = pg[c * M + e];
    any = any || g[c] != 0;
  }
  if (!any) return;
  const Reads r = cube_reads(level_at(pd, e), K, nearest, d_grad);
  double du = 0, dv = 0, dD = 0;
  for (int j = 0; j < r.n; ++j) {
    const int64_t k = r.k[j];
    const CubeLevel& lv = L[k];
    int64_t a;
    double dfx, dfy;
    Tap t;
    if (inner_tap(lv, f, u, v, &a, &dfx, &dfy)) {
      // The fast path: four texels of the face, scattered straight into its gradient.
      const scalar_t fx = static_cast<scalar_t>(dfx), fy = static_cast<scalar_t>(dfy);
      const scalar_t w[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
      const scalar_t wl = static_cast<scalar_t>(r.wt[j]);
      const int64_t n = lv.n;
      scalar_t sx = 0, sy = 0, sv = 0;
      for (int64_t c = 0; c < C; ++c) {
        const scalar_t* pp = lp[k] + c * lv.plane + a;
        const scalar_t t0 = pp[0], t1 = pp[1], t2 = pp[n], t3 = pp[n + 1];
        sx += g[c] * ((1 - fy) * (t1 - t0) + fy * (t3 - t2));
        sy += g[c] * ((1 - fx) * (t2 - t0) + fx * (t3 - t1));
        sv += g[c] * (w[0] * t0 + w[1] * t1 + w[2] * t2 + w[3] * t3);
        if (out.gp[k] != nullptr) {
          scalar_t* gq = out.gp[k] + c * lv.plane + a;
          const scalar_t gw = g[c] * wl;
          gq[0] += gw * w[0];
          gq[1] += gw * w[1];
          gq[n] += gw * w[2];
          gq[n + 1] += gw * w[3];
        }
      }
      du += r.wt[j] * sx * static_cast<double>(n);
      dv += r.wt[j] * sy * static_cast<double>(n);
      dD += r.dwt[j] * sv;
      continue;
    }
    tap_of(lv, f, u, v, &t);
    const scalar_t fx = static_cast<scalar_t>(t.fx), fy = static_cast<scalar_t>(t.fy);
    const scalar_t w[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
    const scalar_t wl = static_cast<scalar_t>(r.wt[j]);
    const scalar_t* p = lp[k];
    scalar_t *gk = out.gp[k], *gr = out.gr[k];
    scalar_t sx = 0, sy = 0, sv = 0;
    for (int64_t c = 0; c < C; ++c) {
      const scalar_t* pp = p + c * lv.plane;
      scalar_t tv[4];
      for (int q = 0; q < 4; ++q) tv[q] = fetch(t.s[q], pp);
      sx += g[c] * ((1 - fy) * (tv[1] - tv[0]) + fy * (tv[3] - tv[2]));
      sy += g[c] * ((1 - fx) * (tv[2] - tv[0]) + fx * (tv[3] - tv[1]));
      sv += g[c] * (w[0] * tv[0] + w[1] * tv[1] + w[2] * tv[2] + w[3] * tv[3]);
      if (gk != nullptr) {
        const scalar_t gw = g[c] * wl;
        for (int q = 0; q < 4; ++q) {
          if (t.s[q].slot < 0)
            gk[t.s[q].a[0] + c * lv.plane] += gw * w[q];
          else
            gr[t.s[q].slot * C + c] += gw * w[q];
        }
      }
    }
    du += r.wt[j] * sx * static_cast<double>(lv.n);
    dv += r.wt[j] * sy * static_cast<double>(lv.n);
    dD += r.dwt[j] * sv;
  }
  if (out.uv) {
    out.uv[2 * e] = static_cast<scalar_t>(du);
    out.uv[2 * e + 1] = static_cast<scalar_t>(dv);
  }
  if (out.D) out.D[e] = static_cast<scalar_t>(dD);
}

}  // namespace

std::tuple<std::vector<Tensor>, Tensor, Tensor> cube_read_backward(
    std::vector<Tensor> levels, std::vector<Tensor> ring_idx, std::vector<Tensor> ring_w,
    Tensor face, Tensor uv, Tensor D, Tensor grad, bool nearest, bool d_grad,
    bool need_levels, bool need_uv, bool need_D) {
  auto L = cube_levels(levels, ring_idx, ring_w, face, uv, D);
  const int64_t K = static_cast<int64_t>(L.size()), C = levels[0].size(1), M = uv.size(0);
  grad = contig(grad);
  DT_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == uv.scalar_type(),
              "cube_read: grad must be [C, M] of uv's dtype");
  std::vector<Tensor> gl(K);
  Tensor guv = need_uv ? zeros({M, 2}, options_of(uv)) : Tensor();
  need_D = need_D && D.numel() > 0;
  Tensor gD = need_D ? zeros({M}, options_of(uv)) : Tensor();
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "cube_read_backward", [&] {
    std::vector<const scalar_t*> lp;
    for (const auto& t : levels) lp.push_back(t.mutable_data_ptr<scalar_t>());
    CubeGrads<scalar_t> out;
    out.gp.assign(K, nullptr);
    out.gr.assign(K, nullptr);
    out.uv = need_uv ? guv.mutable_data_ptr<scalar_t>() : nullptr;
    out.D = need_D ? gD.mutable_data_ptr<scalar_t>() : nullptr;
    const int8_t* pf = face.mutable_data_ptr<int8_t>();
    const scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *pd = (D.numel() ? D.mutable_data_ptr<scalar_t>() : nullptr), *pg = grad.mutable_data_ptr<scalar_t>();
    std::vector<int32_t> keys;
    ScaleBands bands;
    std::vector<std::vector<scalar_t>> rings(K);
    if (need_levels) {
      bands = scale_bands(6 * L[0].P);
      const std::vector<char> read = band_keys(M, K, keys, [&](int64_t e, char* rd) {
        const Reads r = cube_reads(level_at(pd, e), K, nearest, d_grad);
        const int32_t key = cube_key(bands, L, pf[e], puv[2 * e], puv[2 * e + 1], r);
        if (key >= 0)
          for (int j = 0; j < r.n; ++j) rd[r.k[j]] = 1;
        return key;
      });
      for (int64_t k = 0; k < K; ++k) {
        if (!read[k]) continue;
        gl[k] = zeros_like(levels[k]);
        out.gp[k] = gl[k].template mutable_data_ptr<scalar_t>();
        rings[k].assign(static_cast<size_t>(6 * L[k].ring * C), scalar_t(0));
        out.gr[k] = rings[k].data();
      }
    }
    by_channels(C, [&](auto cc) {
      auto one = [&](int64_t e) {
        backward_point<scalar_t, decltype(cc)::value>(e, C, L, lp, pf, puv, pd, pg, out, M, nearest, d_grad);
      };
      auto ahead = [&](int64_t a) {
        prefetch_point<false>(L, lp, C, pf[a], puv[2 * a], puv[2 * a + 1], level_at(pd, a));
        if (need_levels)
          prefetch_point<true>(L, out.gp, C, pf[a], puv[2 * a], puv[2 * a + 1], level_at(pd, a));
      };
      if (need_levels) {
        run_banded(keys.data(), M, bands.classes, [&](const int64_t* idx, int64_t n) {
          for (int64_t i = 0; i < n; ++i) {
            if (i + kAhead < n) ahead(idx[i + kAhead]);
            one(idx[i]);
          }
        });
      } else {
        parallel_for(0, M, 1024, [&](int64_t lo, int64_t hi) {
          for (int64_t e = lo; e < hi; ++e) {
            if (e + kAhead < hi) ahead(e + kAhead);
            one(e);
          }
        });
      }
    });
    // The gutter slots' gradients onto the texels they were read from (the adjoint of the gutter), in order.
    for (int64_t k = 0; k < K; ++k) {
      if (out.gp[k] == nullptr) continue;
      const CubeLevel& lv = L[k];
      for (int64_t s = 0; s < 6 * lv.ring; ++s)
        for (int q = 0; q < 3; ++q) {
          const double w = lv.rw[3 * s + q];
          if (w == 0) continue;
          const int64_t idx = lv.ri[3 * s + q], fi = idx / lv.plane, a = fi * lv.fstride + (idx - fi * lv.plane);
          for (int64_t c = 0; c < C; ++c) out.gp[k][a + c * lv.plane] += static_cast<scalar_t>(w) * rings[k][s * C + c];
        }
    }
  });
  return {gl, guv, gD};
}

}  // namespace difftex
