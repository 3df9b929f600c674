// One lane group's strands in a thread's scratch, shared by the CPU frame kernel (frame_cpu.cpp) and
// its adjoint (frame_adjoint_cpu.cpp): the layout of a strand's arrays, the Strand views on them,
// and the gather of the model's and the scene's arrays of W strands into the interleaved lanes.
#pragma once

#include <algorithm>
#include <cstdint>

#include "banded/banded_simd.h"
#include "common/interleave.h"
#include "frame/frame.h"

namespace ams_torch {
namespace frame {

// Offsets (in values per lane) of one strand's arrays in the scratch; ``total`` is where a caller
// that needs more (the adjoint) continues with ``take``.
struct StrandLayout {
  int64_t rest, mass, drag, stiffness[3], rest_length[3], integrity, angular, segment, pinned;
  int64_t x, v, ghost_rest, sag_offset, ext, a, b, force, ghost, ghost_velocity, total = 0;
  int64_t take(int64_t count) {
    const int64_t at = total;
    total += count;
    return at;
  }
  explicit StrandLayout(int64_t n) {
    rest = take(3 * n);
    mass = take(n);
    drag = take(n);
    for (int k = 0; k < 3; ++k) stiffness[k] = take(n - 1 - k);
    for (int k = 0; k < 3; ++k) rest_length[k] = take(n - 1 - k);
    integrity = take(n);
    angular = take(n - 1);
    segment = take(n);
    pinned = take(1);
    for (int64_t* f : {&x, &v, &ghost_rest, &sag_offset, &ext}) *f = take(3 * n);
    a = take(banded::kRowElems * n);
    for (int64_t* f : {&b, &force, &ghost, &ghost_velocity}) *f = take(3 * n);
  }
};

// The Strand views of N particles on the scratch ``sc`` laid out by ``lay``.
template <class V, class T>
void bind_strand(Strand<V, T>& st, T* sc, const StrandLayout& lay, int64_t n, bool has_ext) {
  constexpr int64_t W = int64_t(sizeof(V) / sizeof(T));
  auto view = [&](int64_t offset) { return Lanes<V, T>{sc + offset * W, W}; };
  st.n = n;
  st.rest = view(lay.rest);
  st.mass = view(lay.mass);
  st.drag = view(lay.drag);
  for (int k = 0; k < 3; ++k) {
    st.stiffness[k] = view(lay.stiffness[k]);
    st.rest_length[k] = view(lay.rest_length[k]);
  }
  st.integrity = view(lay.integrity);
  st.angular = view(lay.angular);
  st.segment = view(lay.segment);
  st.x = view(lay.x);
  st.v = view(lay.v);
  st.ghost_rest = view(lay.ghost_rest);
  st.sag_offset = view(lay.sag_offset);
  st.ext = view(lay.ext);
  st.has_ext = has_ext;
  st.a = view(lay.a);
  st.b = view(lay.b);
  st.force = view(lay.force);
  st.ghost = view(lay.ghost);
  st.ghost_velocity = view(lay.ghost_velocity);
}

// Interleave the (B, S, N, 3) array ``base`` of scene ``b``'s strands ``strand`` (W of them) into the
// scratch at ``offset``.
template <class T, int64_t W>
void gather_scene_array(T* sc, int64_t offset, const T* base, int64_t b, const int64_t* strand, int64_t S,
                        int64_t N) {
  const T* src[W];
  for (int64_t l = 0; l < W; ++l) src[l] = base + (b * S + strand[l]) * 3 * N;
  banded::interleave<T, W>(sc + offset * W, src, 3 * N);
}

// Interleave the model's arrays of the W strands ``strand`` (padded with a real strand) and the
// state of scene ``b`` into the scratch, and set the lanes' pinned counts.
template <class V, class T>
void gather_strands(const FrameArgs<T>& args, const FrameSettings& cfg, const StrandLayout& lay, T* sc, int64_t b,
                    const int64_t* strand, Strand<V, T>& st) {
  constexpr int64_t W = int64_t(sizeof(V) / sizeof(T));
  const int64_t S = args.strands, N = args.particles;
  const bool nonhookean = cfg.integrity_model == kIntegrityNonHookean;
  const T* src[W];
  auto gather_model = [&](const T* base, int64_t per_strand, int64_t offset) {
    for (int64_t l = 0; l < W; ++l) src[l] = base + strand[l] * per_strand;
    banded::interleave<T, W>(sc + offset * W, src, per_strand);
  };
  auto gather_scene = [&](const T* base, int64_t offset) { gather_scene_array<T, W>(sc, offset, base, b, strand, S, N); };
  gather_model(args.rest_positions, 3 * N, lay.rest);
  gather_model(args.mass, N, lay.mass);
  gather_model(args.drag, N, lay.drag);
  for (int k = 0; k < 3; ++k) {
    gather_model(args.stiffness[k], N - 1 - k, lay.stiffness[k]);
    gather_model(args.rest_length[k], N - 1 - k, lay.rest_length[k]);
  }
  if (cfg.integrity_model != kIntegrityNone) gather_model(args.integrity, N, lay.integrity);
  if (cfg.angular) gather_model(args.angular, N - 1, lay.angular);
  if (nonhookean) gather_model(args.segment_length, N, lay.segment);
  gather_scene(args.x, lay.x);
  gather_scene(args.v, lay.v);
  gather_scene(args.ghost_rest, lay.ghost_rest);
  if (nonhookean) gather_scene(args.sag_offset, lay.sag_offset);
  if (args.external_force != nullptr) gather_scene(args.external_force, lay.ext);
  T* pinned = sc + lay.pinned * W;
  int64_t pinned_max = 0;
  for (int64_t l = 0; l < W; ++l) {
    const int64_t p = std::min<int64_t>(std::max<int64_t>(args.num_pinned[strand[l]], 0), N);
    pinned[l] = T(p);
    pinned_max = std::max(pinned_max, p);
  }
  st.pinned = *reinterpret_cast<const V*>(pinned);
  st.pinned_max = int(pinned_max);
}

}  // namespace frame
}  // namespace ams_torch
