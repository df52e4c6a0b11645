// The ripmap filter on the CPU (filters/ripmap.py's native path; the torch
// path there, mip_blend nested over separable_sample, stays the tested
// reference): the build of the levels a view reads, the read (forward and
// first-order backward) and the build's adjoint.
//
// Levels: (i, j) is i width halvings and j height halvings of the base, each
// halving pyramid/mipmap.py _down_axis (the pair average on an even side,
// the area-weighted box of three on an odd one). Halvings along different
// axes commute, so a level is built from its left neighbour in the row
// (i - 1, j), the first column from the level above; only the levels a view
// reads and those on their way are built.
//
// Read: per axis the levels of common.h reads_of (floor D and floor D + 1,
// or with d_grad the level below an integer D > 0 at weight 0, as
// mip_blend), so four bilinear reads (wrap and border as every other read)
// blended by the product of the two axes' weights.
//
// Backward: the uv / level gradients per point, threaded over points; the
// level gradients scattered by threads that each own a fraction of every
// level's rows (every thread walks every point and writes only its rows:
// no lock, the same result for any thread count).
#include "boxes.h"
#include "common.h"

#include "stable.h"

#include <array>

namespace difftex {
namespace {

// The taps of one halving of a side of n texels, as gathers: out[o] = sum_t w[o][t] in[idx[o][t]] (3 taps, unused
// ones weight 0 on a repeated index, as mipmap.py _odd_taps), and the transpose in[x] += sum over (o, w) of
// adj[x]. Even n: out[o] = (in[2o] + in[2o + 1]) * 0.5.
struct Halving {
  int64_t n, m;
  bool even;
  std::vector<std::array<int64_t, 3>> idx;
  std::vector<std::array<double, 3>> w;
  std::vector<std::array<int64_t, 2>> adj_idx;  // per fine texel: the outputs it feeds (-1: none)
  std::vector<std::array<double, 2>> adj_w;
};

Halving halving(int64_t n) {
  Halving h;
  h.n = n;
  h.m = (n + 1) / 2;
  h.even = n % 2 == 0;
  h.idx.resize(h.m);
  h.w.resize(h.m);
  h.adj_idx.assign(n, {-1, -1});
  h.adj_w.assign(n, {0.0, 0.0});
  for (int64_t o = 0; o < h.m; ++o) {
    if (h.even) {
      h.idx[o] = {2 * o, 2 * o + 1, 2 * o + 1};
      h.w[o] = {0.5, 0.5, 0.0};
    } else {
      // Units of 1/m: output o covers [o n, (o + 1) n), source texel i covers [i m, (i + 1) m).
      const int64_t lo = o * n, hi = (o + 1) * n;
      int q = 0;
      for (int64_t i = lo / h.m; i < std::min((hi + h.m - 1) / h.m, n) && q < 3; ++i) {
        const int64_t overlap = std::min(hi, (i + 1) * h.m) - std::max(lo, i * h.m);
        if (overlap > 0) {
          h.idx[o][q] = i;
          h.w[o][q] = static_cast<double>(overlap) / static_cast<double>(n);
          ++q;
        }
      }
      for (; q < 3; ++q) {
        h.idx[o][q] = h.idx[o][q - 1];
        h.w[o][q] = 0.0;
      }
    }
    for (int t = 0; t < 3; ++t) {
      if (h.w[o][t] == 0.0) continue;
      auto& a = h.adj_idx[h.idx[o][t]];
      auto& b = h.adj_w[h.idx[o][t]];
      const int s = a[0] < 0 ? 0 : 1;
      a[s] = o;
      b[s] = h.w[o][t];
    }
  }
  return h;
}

// One halving of x [C, h, w] along the width (axis 1) or the height (axis 0).
template <typename scalar_t>
Tensor halve(const Tensor& x, int axis) {
  const int64_t C = x.size(0), h = x.size(1), w = x.size(2);
  const Halving hv = halving(axis == 1 ? w : h);
  const int64_t oh = axis == 1 ? h : hv.m, ow = axis == 1 ? hv.m : w;
  auto out = empty({C, oh, ow}, options_of(x));
  const scalar_t* px = x.mutable_data_ptr<scalar_t>();
  scalar_t* po = out.mutable_data_ptr<scalar_t>();
  parallel_for(0, C * oh, 16, [&](int64_t lo, int64_t hi) {
    for (int64_t r = lo; r < hi; ++r) {
      const int64_t c = r / oh, y = r % oh;
      scalar_t* o = po + r * ow;
      if (axis == 1) {
        const scalar_t* s = px + (c * h + y) * w;
        if (hv.even) {
          for (int64_t a = 0; a < ow; ++a) o[a] = (s[2 * a] + s[2 * a + 1]) * static_cast<scalar_t>(0.5);
        } else {
          for (int64_t a = 0; a < ow; ++a) {
            const auto& i = hv.idx[a];
            const auto& wt = hv.w[a];
            o[a] = s[i[0]] * static_cast<scalar_t>(wt[0]) + s[i[1]] * static_cast<scalar_t>(wt[1]) +
                   s[i[2]] * static_cast<scalar_t>(wt[2]);
          }
        }
      } else {
        const auto& i = hv.idx[y];
        const auto& wt = hv.w[y];
        const scalar_t* s0 = px + (c * h + i[0]) * w;
        const scalar_t* s1 = px + (c * h + i[1]) * w;
        const scalar_t* s2 = px + (c * h + i[2]) * w;
        if (hv.even) {
          for (int64_t a = 0; a < ow; ++a) o[a] = (s0[a] + s1[a]) * static_cast<scalar_t>(0.5);
        } else {
          const scalar_t w0 = static_cast<scalar_t>(wt[0]), w1 = static_cast<scalar_t>(wt[1]),
                         w2 = static_cast<scalar_t>(wt[2]);
          for (int64_t a = 0; a < ow; ++a) o[a] = s0[a] * w0 + s1[a] * w1 + s2[a] * w2;
        }
      }
    }
  });
  return out;
}

// fine [C, h, w] += the transpose of halve(., axis) applied to coarse; with assign, fine = it (no zero-filled
// buffer to add into where a level on the way has no gradient of its own).
template <typename scalar_t>
void halve_adjoint(Tensor& fine, const Tensor& coarse, int axis, bool assign) {
  const int64_t C = fine.size(0), h = fine.size(1), w = fine.size(2);
  const Halving hv = halving(axis == 1 ? w : h);
  const int64_t ch = coarse.size(1), cw = coarse.size(2);
  scalar_t* pf = fine.mutable_data_ptr<scalar_t>();
  const scalar_t* pc = coarse.mutable_data_ptr<scalar_t>();
  parallel_for(0, C * h, 16, [&](int64_t lo, int64_t hi) {
    for (int64_t r = lo; r < hi; ++r) {
      const int64_t c = r / h, y = r % h;
      scalar_t* f = pf + r * w;
      if (axis == 1) {
        const scalar_t* s = pc + (c * ch + y) * cw;
        for (int64_t x = 0; x < w; ++x) {
          const auto& i = hv.adj_idx[x];
          const auto& wt = hv.adj_w[x];
          scalar_t add = s[i[0]] * static_cast<scalar_t>(wt[0]);
          if (i[1] >= 0) add += s[i[1]] * static_cast<scalar_t>(wt[1]);
          f[x] = assign ? add : f[x] + add;
        }
      } else {
        const auto& i = hv.adj_idx[y];
        const auto& wt = hv.adj_w[y];
        const scalar_t* s0 = pc + (c * ch + i[0]) * cw;
        const scalar_t w0 = static_cast<scalar_t>(wt[0]);
        if (i[1] >= 0) {
          const scalar_t* s1 = pc + (c * ch + i[1]) * cw;
          const scalar_t w1 = static_cast<scalar_t>(wt[1]);
          if (assign)
            for (int64_t x = 0; x < w; ++x) f[x] = s0[x] * w0 + s1[x] * w1;
          else
            for (int64_t x = 0; x < w; ++x) f[x] += s0[x] * w0 + s1[x] * w1;
        } else if (assign) {
          for (int64_t x = 0; x < w; ++x) f[x] = s0[x] * w0;
        } else {
          for (int64_t x = 0; x < w; ++x) f[x] += s0[x] * w0;
        }
      }
    }
  });
}

bool present(const Tensor& t) { return t.defined() && t.numel() > 0; }

struct Shapes {
  int64_t C, n_u, n_v;
  std::vector<Level> L;  // per flat level; h = w = 0 where absent
  std::vector<const void*> ptr;
};

Shapes check_levels(const std::vector<Tensor>& levels, int64_t n_u, const Tensor& uv,
                    const Tensor& Du, const Tensor& Dv) {
  Shapes s;
  DT_CHECK(n_u >= 1 && !levels.empty() && static_cast<int64_t>(levels.size()) % n_u == 0,
              "ripmap_read: expected n_u * n_v levels");
  s.n_u = n_u;
  s.n_v = static_cast<int64_t>(levels.size()) / n_u;
  const int64_t M = uv.size(0);
  DT_CHECK(uv.dim() == 2 && uv.size(1) == 2 && uv.is_contiguous() && uv.is_cpu(),
              "ripmap_read: uv must be contiguous CPU [M, 2]");
  for (const auto* d : {&Du, &Dv})
    DT_CHECK(d->dim() == 1 && d->size(0) == M && d->is_contiguous() && d->scalar_type() == uv.scalar_type(),
                "ripmap_read: Du, Dv must be contiguous [M] of uv's dtype");
  s.C = -1;
  for (const auto& t : levels) {
    if (!present(t)) {
      s.L.push_back({0, 0, 0});
      s.ptr.push_back(nullptr);
      continue;
    }
    DT_CHECK(t.dim() == 3 && t.is_contiguous() && t.scalar_type() == uv.scalar_type() && t.is_cpu() &&
                    (s.C < 0 || t.size(0) == s.C),
                "ripmap_read: levels must be contiguous CPU [C, h, w] of uv's dtype");
    s.C = t.size(0);
    s.L.push_back({t.size(1), t.size(2), t.size(1) * t.size(2)});
    s.ptr.push_back(t.data_ptr());
  }
  DT_CHECK(s.C > 0, "ripmap_read: no level given");
  return s;
}

// The (up to) four levels of a point: flat index, weight, d weight / dDu, d weight / dDv.
struct Quad {
  int n;
  int64_t lv[4];
  double w[4], du[4], dv[4];
};

DT_INLINE Quad quad_of(double Du, double Dv, const Shapes& s, bool d_grad) {
  const Reads ru = reads_of(Du, s.n_u, false, d_grad), rv = reads_of(Dv, s.n_v, false, d_grad);
  Quad q;
  q.n = 0;
  for (int b = 0; b < rv.n; ++b)
    for (int a = 0; a < ru.n; ++a) {
      q.lv[q.n] = rv.k[b] * s.n_u + ru.k[a];
      q.w[q.n] = ru.wt[a] * rv.wt[b];
      q.du[q.n] = ru.dwt[a] * rv.wt[b];
      q.dv[q.n] = ru.wt[a] * rv.dwt[b];
      ++q.n;
    }
  return q;
}

}  // namespace

std::vector<Tensor> ripmap_build(Tensor texture, int64_t n_u, int64_t n_v, std::vector<bool> wanted) {
  DT_CHECK(texture.dim() == 3 && texture.is_cpu(), "ripmap_build: texture must be CPU [C, H, W]");
  DT_CHECK(n_u >= 1 && n_v >= 1 && static_cast<int64_t>(wanted.size()) == n_u * n_v,
              "ripmap_build: wanted must hold n_u * n_v flags");
  std::vector<Tensor> out(n_u * n_v);
  std::vector<int64_t> last(n_v, -1);  // the last level wanted in each row
  int64_t top = -1;
  for (int64_t j = 0; j < n_v; ++j)
    for (int64_t i = 0; i < n_u; ++i)
      if (wanted[j * n_u + i]) last[j] = i, top = j;
  if (top < 0) return out;
  DT_DISPATCH_FLOATING_TYPES(texture.scalar_type(), "ripmap_build", [&] {
    Tensor first = contig(texture);
    for (int64_t j = 0; j <= top; ++j) {
      if (j > 0) first = halve<scalar_t>(first, 0);
      Tensor x = first;
      if (last[j] >= 0) out[j * n_u] = x;
      for (int64_t i = 1; i <= last[j]; ++i) {
        x = halve<scalar_t>(x, 1);
        out[j * n_u + i] = x;
      }
    }
  });
  return out;
}

Tensor ripmap_adjoint(std::vector<Tensor> grads, int64_t n_u, int64_t n_v, int64_t H, int64_t W) {
  DT_CHECK(static_cast<int64_t>(grads.size()) == n_u * n_v, "ripmap_adjoint: expected n_u * n_v gradients");
  auto size_of = [&](int64_t i, int64_t j) {
    return std::pair<int64_t, int64_t>{(H + (int64_t{1} << j) - 1) >> j, (W + (int64_t{1} << i) - 1) >> i};
  };
  Tensor any;
  for (const auto& g : grads)
    if (present(g)) any = g;
  DT_CHECK(any.defined(), "ripmap_adjoint: no gradient given");
  const int64_t C = any.size(0);
  Tensor col;  // the running total of the column level (0, j + 1)
  DT_DISPATCH_FLOATING_TYPES(any.scalar_type(), "ripmap_adjoint", [&] {
    for (int64_t j = n_v - 1; j >= 0; --j) {
      // Row j, right to left, into (0, j).
      Tensor acc;
      for (int64_t i = n_u - 1; i >= 0; --i) {
        const Tensor& g = grads[j * n_u + i];
        if (acc.defined()) {
          auto [h, w] = size_of(i, j);
          Tensor fine = present(g) ? contig(g) : empty({C, h, w}, options_of(any));
          halve_adjoint<scalar_t>(fine, acc, 1, !present(g));
          acc = fine;
        } else if (present(g)) {
          acc = contig(g);
        }
      }
      if (col.defined()) {
        auto [h, w] = size_of(0, j);
        Tensor fine = acc.defined() ? acc : empty({C, h, w}, options_of(any));
        halve_adjoint<scalar_t>(fine, col, 0, !acc.defined());
        col = fine;
      } else if (acc.defined()) {
        col = acc;
      }
    }
  });
  return col;
}

Tensor ripmap_read(std::vector<Tensor> levels, int64_t n_u, Tensor uv, Tensor Du,
                          Tensor Dv, const ReadOptions& opts) {
  const Shapes s = check_levels(levels, n_u, uv, Du, Dv);
  const int64_t C = s.C, M = uv.size(0), wrap_u = opts.wrap_u, wrap_v = opts.wrap_v;
  auto out = empty({C, M}, options_of(uv));
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "ripmap_read", [&] {
    const scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *pu = Du.mutable_data_ptr<scalar_t>(), *pv = Dv.mutable_data_ptr<scalar_t>();
    scalar_t* po = out.mutable_data_ptr<scalar_t>();
    const scalar_t bv = static_cast<scalar_t>(opts.border);
    parallel_for(0, M, 512, [&](int64_t lo, int64_t hi) {
      std::vector<double> acc(C);
      for (int64_t e = lo; e < hi; ++e) {
        const double u = puv[2 * e], v = puv[2 * e + 1];
        if (!std::isfinite(u) || !std::isfinite(v)) {
          for (int64_t c = 0; c < C; ++c) po[c * M + e] = std::numeric_limits<scalar_t>::quiet_NaN();
          continue;
        }
        const Quad q = quad_of(pu[e], pv[e], s, opts.d_grad);
        const Folded fu = fold(u, static_cast<int>(wrap_u)), fv = fold(v, static_cast<int>(wrap_v));
        std::fill(acc.begin(), acc.end(), 0.0);
        for (int t = 0; t < q.n; ++t) {
          const Level& lv = s.L[q.lv[t]];
          DT_CHECK(lv.h > 0, "ripmap_read: a point reads a level that was not given");
          const Bilinear b = taps_folded(fu, fv, lv.h, lv.w, static_cast<int>(wrap_u), static_cast<int>(wrap_v));
          const scalar_t wl = static_cast<scalar_t>(q.w[t]);
          const scalar_t wts[4] = {static_cast<scalar_t>((1 - b.fx) * (1 - b.fy)),
                                   static_cast<scalar_t>(b.fx * (1 - b.fy)), static_cast<scalar_t>((1 - b.fx) * b.fy),
                                   static_cast<scalar_t>(b.fx * b.fy)};
          const scalar_t* p = static_cast<const scalar_t*>(s.ptr[q.lv[t]]);
          for (int64_t c = 0; c < C; ++c) {
            const scalar_t* pp = p + c * lv.plane;
            scalar_t val = 0;
            for (int k = 0; k < 4; ++k) val += wts[k] * (b.inside[k] ? pp[b.idx[k]] : bv);
            acc[c] += static_cast<double>(wl * val);
          }
        }
        for (int64_t c = 0; c < C; ++c) po[c * M + e] = static_cast<scalar_t>(acc[c]);
      }
    });
  });
  return out;
}

std::tuple<std::vector<Tensor>, Tensor, Tensor, Tensor> ripmap_read_backward(
    std::vector<Tensor> levels, int64_t n_u, Tensor uv, Tensor Du, Tensor Dv,
    Tensor grad, const ReadOptions& opts, bool need_levels, bool need_uv, bool need_D) {
  const Shapes s = check_levels(levels, n_u, uv, Du, Dv);
  const int64_t C = s.C, M = uv.size(0), K = static_cast<int64_t>(levels.size());
  const int wrap_u = static_cast<int>(opts.wrap_u), wrap_v = static_cast<int>(opts.wrap_v);
  DT_CHECK(grad.dim() == 2 && grad.size(0) == C && grad.size(1) == M && grad.scalar_type() == uv.scalar_type(),
              "ripmap_read: grad must be [C, M] of uv's dtype");
  const int64_t gsc = grad.stride(0), gsm = grad.stride(1);
  std::vector<Tensor> gl(K);
  Tensor guv = need_uv ? zeros({M, 2}, options_of(uv)) : Tensor();
  Tensor gu = need_D ? zeros({M}, options_of(uv)) : Tensor();
  Tensor gv = need_D ? zeros({M}, options_of(uv)) : Tensor();
  DT_DISPATCH_FLOATING_TYPES(uv.scalar_type(), "ripmap_read_backward", [&] {
    const scalar_t *puv = uv.mutable_data_ptr<scalar_t>(), *pu = Du.mutable_data_ptr<scalar_t>(), *pv = Dv.mutable_data_ptr<scalar_t>(),
                   *pg = grad.mutable_data_ptr<scalar_t>();
    const scalar_t bv = static_cast<scalar_t>(opts.border);
    if (need_uv || need_D) {
      scalar_t* ouv = need_uv ? guv.mutable_data_ptr<scalar_t>() : nullptr;
      scalar_t* ou = need_D ? gu.mutable_data_ptr<scalar_t>() : nullptr;
      scalar_t* ov = need_D ? gv.mutable_data_ptr<scalar_t>() : nullptr;
      parallel_for(0, M, 512, [&](int64_t lo, int64_t hi) {
        for (int64_t e = lo; e < hi; ++e) {
          const double u = puv[2 * e], v = puv[2 * e + 1];
          if (!std::isfinite(u) || !std::isfinite(v)) continue;
          const Quad q = quad_of(pu[e], pv[e], s, opts.d_grad);
          const Folded fu = fold(u, wrap_u), fv = fold(v, wrap_v);
          double du = 0, dv = 0, dDu = 0, dDv = 0;
          for (int t = 0; t < q.n; ++t) {
            const Level& lv = s.L[q.lv[t]];
            DT_CHECK(lv.h > 0, "ripmap_read: a point reads a level that was not given");
            const Bilinear b = taps_folded(fu, fv, lv.h, lv.w, wrap_u, wrap_v);
            const scalar_t* p = static_cast<const scalar_t*>(s.ptr[q.lv[t]]);
            const double fx = b.fx, fy = b.fy;
            double sx = 0, sy = 0, sv = 0;
            for (int64_t c = 0; c < C; ++c) {
              const scalar_t* pp = p + c * lv.plane;
              double tv[4];
              for (int k = 0; k < 4; ++k) tv[k] = b.inside[k] ? static_cast<double>(pp[b.idx[k]]) : bv;
              const double g = pg[c * gsc + e * gsm];
              sx += g * ((1 - fy) * (tv[1] - tv[0]) + fy * (tv[3] - tv[2]));
              sy += g * ((1 - fx) * (tv[2] - tv[0]) + fx * (tv[3] - tv[1]));
              sv += g * ((1 - fx) * (1 - fy) * tv[0] + fx * (1 - fy) * tv[1] + (1 - fx) * fy * tv[2] + fx * fy * tv[3]);
            }
            du += q.w[t] * sx * b.sx * static_cast<double>(lv.w);
            dv += q.w[t] * sy * b.sy * static_cast<double>(lv.h);
            dDu += q.du[t] * sv;
            dDv += q.dv[t] * sv;
          }
          if (ouv) {
            ouv[2 * e] = static_cast<scalar_t>(du);
            ouv[2 * e + 1] = static_cast<scalar_t>(dv);
          }
          if (ou) {
            ou[e] = static_cast<scalar_t>(dDu);
            ov[e] = static_cast<scalar_t>(dDv);
          }
        }
      });
    }
    if (need_levels) {
      // The levels read (their gradients are allocated, zeroed, only for those).
      std::vector<char> read(K, 0);
      for (int64_t e = 0; e < M; ++e) {
        if (!std::isfinite(static_cast<double>(puv[2 * e])) || !std::isfinite(static_cast<double>(puv[2 * e + 1])))
          continue;
        const Quad q = quad_of(pu[e], pv[e], s, opts.d_grad);
        for (int t = 0; t < q.n; ++t) read[q.lv[t]] = 1;
      }
      std::vector<scalar_t*> gp(K, nullptr);
      for (int64_t k = 0; k < K; ++k) {
        if (!read[k]) continue;
        DT_CHECK(s.L[k].h > 0, "ripmap_read: a point reads a level that was not given");
        gl[k] = zeros({C, s.L[k].h, s.L[k].w}, options_of(uv));
        gp[k] = gl[k].template mutable_data_ptr<scalar_t>();
      }
      const int64_t T = std::max<int64_t>(1, std::min<int64_t>(get_num_threads(), M / 256));
      parallel_for(0, T, 1, [&](int64_t t0, int64_t t1) {
        for (int64_t t = t0; t < t1; ++t) {
          for (int64_t e = 0; e < M; ++e) {
            const double u = puv[2 * e], v = puv[2 * e + 1];
            if (!std::isfinite(u) || !std::isfinite(v)) continue;
            const Quad q = quad_of(pu[e], pv[e], s, opts.d_grad);
            const Folded fu = fold(u, wrap_u), fv = fold(v, wrap_v);
            for (int k = 0; k < q.n; ++k) {
              const Level& lv = s.L[q.lv[k]];
              // Rows [h t / T, h (t + 1) / T) of every level are this thread's.
              const int64_t r0 = lv.h * t / T, r1 = lv.h * (t + 1) / T;
              const Bilinear b = taps_folded(fu, fv, lv.h, lv.w, wrap_u, wrap_v);
              const bool own0 = b.idx[0] / lv.w >= r0 && b.idx[0] / lv.w < r1;
              const bool own1 = b.idx[2] / lv.w >= r0 && b.idx[2] / lv.w < r1;
              if (!own0 && !own1) continue;
              const double fx = b.fx, fy = b.fy, wl = q.w[k];
              const double wts[4] = {wl * (1 - fx) * (1 - fy), wl * fx * (1 - fy), wl * (1 - fx) * fy, wl * fx * fy};
              scalar_t* gk = gp[q.lv[k]];
              for (int64_t c = 0; c < C; ++c) {
                scalar_t* gq = gk + c * lv.plane;
                const double g = pg[c * gsc + e * gsm];
                for (int j = 0; j < 4; ++j)
                  if (b.inside[j] && (j < 2 ? own0 : own1)) gq[b.idx[j]] += static_cast<scalar_t>(g * wts[j]);
              }
            }
          }
        }
      });
    }
  });
  return {gl, guv, gu, gv};
}

}  // namespace difftex
