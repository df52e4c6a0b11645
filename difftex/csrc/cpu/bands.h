// The lock-free scatter of a texture gradient over threads, shared by the
// single-level backward (single.cpp) and the mip taps' backward (taps.cpp).
//
// Points share texels, so their gradient scatters cannot simply run in
// parallel. Instead of a lock, atomics or one texture-sized buffer per
// thread (zeroed and summed after: as costly as the scatter itself on a
// 1024^2 texture), the texture rows are cut into bands and every point is
// given the band where the rows it writes begin ("its key"). A band's
// points write only inside it and the band after it (cyclically for
// "repeat"): a key is only given where that holds. So bands of the same
// parity never write the same texel, and the even bands run in parallel,
// then the odd ones. A class groups bands that may run together (the
// single-level read: its two parities; the taps: two per band scale, see
// taps.cpp); classes run one after another.
//
// The result is deterministic and independent of the thread count: a texel
// receives its terms from at most two bands, in class order, and a band's
// points always run in index order on one thread; threads only decide
// which bands run where.
#pragma once

#include "stable.h"

#include <algorithm>
#include <cstdint>
#include <vector>

namespace difftex {

// The number of bands that a level of h rows is cut into where a point
// writes at most `reach` consecutive rows: the largest power of two (at
// most `cap`) whose every band has at least `reach` rows; 1 (one band, no
// split) where two would not.
inline int64_t band_count(int64_t h, int64_t reach, int64_t cap = 512) {
  int64_t nb = 1;
  while (nb * 2 <= cap && nb * 2 * reach <= h) nb *= 2;
  return nb;
}

// The bands of a level-gradient scatter at several scales (taps.cpp,
// cube.cpp): nb0 bands (scale 0) of h0 rows, where a point writes at most
// four consecutive rows, then nb0 / 2, ... down to 2. A point is keyed at
// the finest scale whose band holds its rows; bands of scale s are classes
// 2s (even) and 2s + 1 (odd); the last key (serial) is for the points no
// scale holds, run serially at the end.
struct ScaleBands {
  int64_t nb0, scales, serial;  // serial: the last band's key
  std::vector<int64_t> offset;  // first key of each scale
  std::vector<int32_t> classes;
};

inline ScaleBands scale_bands(int64_t h0) {
  ScaleBands t;
  // Four rows of level 0 (two taps and a margin row on each side) fit in the finest band.
  t.nb0 = band_count(h0, 4);
  t.scales = 0;
  for (int64_t nb = t.nb0; nb >= 2; nb /= 2) {
    t.offset.push_back(static_cast<int64_t>(t.classes.size()));
    for (int64_t j = 0; j < nb; ++j) t.classes.push_back(static_cast<int32_t>(2 * t.scales + j % 2));
    ++t.scales;
  }
  t.serial = static_cast<int64_t>(t.classes.size());
  t.classes.push_back(static_cast<int32_t>(2 * t.scales));
  return t;
}

// Every point's band key (keys[e], -1: writes nothing) and which of the K
// levels any point reads, in one threaded pass: key_range(lo, hi, keys, read)
// sets keys[e] for e in [lo, hi) and read[k] = 1 for each level k a point
// with a key reads.
template <typename KeyRange>
std::vector<char> band_key_ranges(int64_t M, int64_t K, std::vector<int32_t>& keys, KeyRange key_range) {
  keys.resize(M);
  const int64_t T = std::max<int64_t>(1, get_num_threads());
  std::vector<std::vector<char>> read(T, std::vector<char>(K, 0));
  parallel_for(0, M, 4096, [&](int64_t lo, int64_t hi) {
    key_range(lo, hi, keys.data(), read[std::min<int64_t>(get_thread_num(), T - 1)].data());
  });
  std::vector<char> any(K, 0);
  for (const auto& rd : read)
    for (int64_t k = 0; k < K; ++k) any[k] = any[k] || rd[k];
  return any;
}

// band_key_ranges one point at a time: key_of(e, read) returns point e's key
// and sets read[k] = 1 for each level k it reads.
template <typename KeyOf>
std::vector<char> band_keys(int64_t M, int64_t K, std::vector<int32_t>& keys, KeyOf key_of) {
  return band_key_ranges(M, K, keys, [&](int64_t lo, int64_t hi, int32_t* out, char* rd) {
    for (int64_t e = lo; e < hi; ++e) out[e] = key_of(e, rd);
  });
}

// The band of row r in [0, h) of a level cut into nb bands.
inline int64_t band_of(int64_t r, int64_t h, int64_t nb) { return r * nb / h; }

// Runs work(idx, n) over every point e in [0, M) with keys[e] >= 0 (idx:
// n of them, in order), on parallel_for threads. keys[e] is a band in [0, classes.size()),
// classes[band] its class; the classes run in order, the bands of one
// class in parallel (grouped by point count, so that threads get similar
// work), each band's points in index order. Below `serial_below` points a
// class runs on one thread. The points are sorted by band once (a stable
// counting sort in fixed chunks, threaded); each group then walks its own
// bands' points. Bands of one class never write the same texel, so the
// order between them is free, and a texel's sums keep their order.
template <typename Work>
void run_banded(const int32_t* keys, int64_t M, const std::vector<int32_t>& classes, Work&& work,
                int64_t serial_below = 1024) {
  const int64_t nbands = static_cast<int64_t>(classes.size());
  const int64_t T = std::max<int64_t>(1, get_num_threads());
  // Fixed chunks of points, so that the sort's order does not depend on which thread takes which chunk.
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(T, M >> 15));
  const int64_t step = (M + chunks - 1) / chunks;
  std::vector<int64_t> hist(chunks * nbands, 0);  // hist[c * nbands + b]: chunk c's points in band b
  parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      int64_t* h = hist.data() + c * nbands;
      for (int64_t e = c * step, end = std::min(M, e + step); e < end; ++e)
        if (keys[e] >= 0) ++h[keys[e]];
    }
  });
  // start[b]: band b's first slot in `order`; hist becomes each chunk's first slot in each band.
  std::vector<int64_t> start(nbands + 1, 0);
  for (int64_t b = 0; b < nbands; ++b) {
    int64_t at = start[b];
    for (int64_t c = 0; c < chunks; ++c) {
      const int64_t n = hist[c * nbands + b];
      hist[c * nbands + b] = at;
      at += n;
    }
    start[b + 1] = at;
  }
  std::vector<int64_t> order(start[nbands]);
  parallel_for(0, chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      int64_t* slot = hist.data() + c * nbands;
      for (int64_t e = c * step, end = std::min(M, e + step); e < end; ++e)
        if (keys[e] >= 0) order[slot[keys[e]]++] = e;
    }
  });
  int32_t P = 0;
  for (int32_t c : classes) P = std::max(P, c + 1);
  std::vector<int64_t> bands;  // the current class's bands with points, in order
  std::vector<int64_t> first;  // first[g]: group g's first entry of `bands`
  for (int32_t p = 0; p < P; ++p) {
    int64_t total = 0;
    bands.clear();
    for (int64_t b = 0; b < nbands; ++b)
      if (classes[b] == p && start[b + 1] > start[b]) total += start[b + 1] - start[b], bands.push_back(b);
    if (total == 0) continue;
    const int64_t busy = static_cast<int64_t>(bands.size());
    const int64_t G = total < serial_below ? 1 : std::min(T, busy);
    // Contiguous runs of bands of about total / G points each.
    first.assign(G + 1, busy);
    int64_t before = 0;
    for (int64_t i = 0, g = 0; i < busy; ++i) {
      const int64_t n = start[bands[i] + 1] - start[bands[i]];
      const int64_t own = std::min<int64_t>(G - 1, (before + n / 2) * G / total);
      while (g <= own) first[g++] = i;
      before += n;
    }
    parallel_for(0, G, 1, [&](int64_t g0, int64_t g1) {
      for (int64_t i = first[g0]; i < first[g1]; ++i)
        // The points go to work in short runs (blocks of the kernels).
        for (int64_t s = start[bands[i]], end = start[bands[i] + 1]; s < end; s += 256)
          work(static_cast<const int64_t*>(order.data() + s), std::min<int64_t>(256, end - s));
    });
  }
}

}  // namespace difftex
