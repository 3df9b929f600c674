// CPU kernel of the fused frame of strand dynamics: op `ams_torch_cpu::frame` (schema and
// shapes in frame_binding.h; arithmetic in frame.h, shared with CUDA).
//
// Work is split into tasks of (scene, group of W strands), W the SIMD width of banded_simd.h
// (8 float / 4 double strands with 32-byte vectors), run by at::parallel_for. A task copies its
// W strands' inputs into a per-thread scratch buffer in a strand-interleaved layout (value e of
// lane l at e·W + l), runs the whole frame there (M substeps of assembly + banded solve +
// position update, then follow-the-leader) on W-lane vectors, and copies x and v out: one
// group's matrix rows, right-hand sides and positions (about 77 N W values: 79 KB at N = 32)
// stay in L1/L2 for the whole frame. The scratch is allocated once per thread and reused across
// calls; nothing is allocated per strand. The last group of a scene is padded with copies of a
// real strand. The M + 1 substep head poses of every scene are computed once per call.
//
// Op `ams_torch_cpu::finish` (finish.h): the frame's end, pinned velocities and speeds
// relative to the head, one pass over the particles, parallel over strands; and
// `ams_torch_cpu::frame_finish`, the frame with its end fused in (each group's results are
// finished as soon as they are copied out).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <optional>
#include <tuple>
#include <vector>

#include "banded/banded_simd.h"
#include "frame/contact_binding.h"
#include "frame/frame.h"
#include "frame/frame_binding.h"
#include "frame/strand_scratch_cpu.h"
#include "common/interleave.h"
#include "common/thread_scratch.h"

namespace ams_torch {
namespace frame {
namespace {

constexpr const char* kOp = "ams_torch_cpu::frame";

using banded::deinterleave;
using banded::interleave;

template <class T>
void run_frame(const FrameArgs<T>& args, const FrameSettings& cfg, int64_t assemble_substep, T* out0, T* out1,
               const FinishArgs<T>* fin = nullptr, const ContactArgs<T>* contact = nullptr) {
  using V = typename banded::LaneVec<T>::type;
  constexpr int64_t W = int64_t(sizeof(V) / sizeof(T));
  const int64_t B = args.scenes, S = args.strands, N = args.particles, M = cfg.substeps;
  // the substep poses of every scene (pose k: the head at the end of substep k − 1)
  std::vector<T> poses(size_t(B * (M + 1) * kPoseElems));
  for (int64_t b = 0; b < B; ++b)
    for (int64_t k = 0; k <= M; ++k)
      substep_pose(args, b, int(k), int(M), cfg.hermite, cfg.dt, poses.data() + (b * (M + 1) + k) * kPoseElems);
  const Material<T> mat{{args.gravity[0], args.gravity[1], args.gravity[2]}, *args.transition, *args.breaking,
                        *args.soft_ratio};
  const StrandLayout lay(N);
  const int64_t groups = (S + W - 1) / W;
  const bool has_ext = args.external_force != nullptr;
  // substep contact: every scene's colliders prepared for every substep, [scene][substep][collider]
  const int64_t C = contact != nullptr ? contact->count : 0;
  std::vector<collide::Prepared<T>> prepared(size_t(std::max<int64_t>(1, B * M * C)));
  for (int64_t b = 0; b < B; ++b)
    for (int64_t k = 0; k < M; ++k)
      for (int64_t c = 0; c < C; ++c)
        collide::prepare_collider(contact_collider(*contact, int(c), int(k)), b, prepared[(b * M + k) * C + c]);

  at::parallel_for(0, B * groups, 1, [&](int64_t t_begin, int64_t t_end) {
    T* sc = static_cast<T*>(ams_torch::thread_scratch(size_t(lay.total * W) * sizeof(T), "frame"));
    Strand<V, T> st;
    bind_strand(st, sc, lay, N, has_ext);

    for (int64_t task = t_begin; task < t_end; ++task) {
      const int64_t b = task / groups, s0 = (task % groups) * W;
      const int64_t lanes = std::min<int64_t>(W, S - s0);
      int64_t strand[W];
      for (int64_t l = 0; l < W; ++l) strand[l] = std::min(s0 + l, S - 1); // pad with a real strand
      gather_strands(args, cfg, lay, sc, b, strand, st);
      const T* scene_poses = poses.data() + b * (M + 1) * kPoseElems;
      T* dst[W];
      if (assemble_substep >= 0) {
        const T* pa = scene_poses + assemble_substep * kPoseElems;
        assemble(st, mat, cfg, pa, pa + kPoseElems);
        mirror_blocks(st.a, N);
        for (int64_t l = 0; l < lanes; ++l) dst[l] = out0 + (b * S + s0 + l) * banded::kRowElems * N;
        deinterleave<T, W>(dst, sc + lay.a * W, banded::kRowElems * N, lanes);
        for (int64_t l = 0; l < lanes; ++l) dst[l] = out1 + (b * S + s0 + l) * 3 * N;
        deinterleave<T, W>(dst, sc + lay.b * W, 3 * N, lanes);
      } else {
        strand_frame(st, mat, cfg, scene_poses, C > 0 ? prepared.data() + b * M * C : nullptr, int(C));
        for (int64_t l = 0; l < lanes; ++l) dst[l] = out0 + (b * S + s0 + l) * 3 * N;
        deinterleave<T, W>(dst, sc + lay.x * W, 3 * N, lanes);
        for (int64_t l = 0; l < lanes; ++l) dst[l] = out1 + (b * S + s0 + l) * 3 * N;
        deinterleave<T, W>(dst, sc + lay.v * W, 3 * N, lanes);
        if (fin != nullptr) // the frame's end on the group's results, while they are in cache
          for (int64_t l = 0; l < lanes; ++l) finish_range(*fin, b * S + s0 + l, 0, N);
      }
    }
  });
}

// Both frame ops: the frame (or one substep's system), and with `finish_pose` the frame's end
// fused in (third output: the speeds; undefined without).
std::tuple<at::Tensor, at::Tensor, at::Tensor> frame_impl(const char* op, const FrameInputs& in,
                                                          const at::TensorList* finish_pose) {
  TORCH_CHECK(in.state[kX].device().is_cpu(), op, ": CPU tensors expected");
  at::Tensor out0, out1; // (not structured bindings: C++17 lambdas cannot capture them)
  std::tie(out0, out1) = frame_outputs(in);
  std::optional<FinishInputs> f;
  if (finish_pose != nullptr) f = fused_finish_inputs(op, in, out0, out1, *finish_pose);
  if (in.scenes > 0 && in.strands > 0) {
    AT_DISPATCH_FLOATING_TYPES(in.state[kX].scalar_type(), "ams_torch_cpu::frame", [&] {
      std::optional<FinishArgs<scalar_t>> fa;
      if (f) fa = finish_args<scalar_t>(*f);
      run_frame<scalar_t>(frame_args<scalar_t>(in), in.settings, in.assemble_substep,
                          out0.mutable_data_ptr<scalar_t>(), out1.mutable_data_ptr<scalar_t>(), fa ? &*fa : nullptr);
    });
  }
  return {out0, out1, f ? f->speed : at::Tensor()};
}

std::tuple<at::Tensor, at::Tensor> frame_cpu(at::TensorList state, const std::optional<at::Tensor>& ext,
                                             at::TensorList model, at::TensorList poses AMS_FRAME_SETTINGS_PARAMS,
                                                 bool hermite, int64_t assemble_substep) {
  const FrameInputs in = check_frame_inputs(kOp, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS, hermite,
      assemble_substep);
  const auto out = frame_impl(kOp, in, nullptr);
  return {std::get<0>(out), std::get<1>(out)};
}

std::tuple<at::Tensor, at::Tensor> frame_contact_cpu(
    at::TensorList state, const std::optional<at::Tensor>& ext, at::TensorList model,
        at::TensorList poses AMS_FRAME_SETTINGS_PARAMS, bool hermite, at::TensorList tensors,
    at::TensorList collider_poses, c10::IntArrayRef ints, c10::ArrayRef<double> floats) {
  constexpr const char* op = "ams_torch_cpu::frame_contact";
  const FrameInputs in = check_frame_inputs(op, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS, hermite, -1);
  TORCH_CHECK(in.state[kX].device().is_cpu(), op, ": CPU tensors expected");
  const ContactInputs cin = check_contact_inputs(op, in, tensors, collider_poses, ints, floats);
  at::Tensor out0, out1;
  std::tie(out0, out1) = frame_outputs(in);
  if (in.scenes > 0 && in.strands > 0) {
    AT_DISPATCH_FLOATING_TYPES(in.state[kX].scalar_type(), op, [&] {
      const ContactArgs<scalar_t> ca = contact_args<scalar_t>(cin);
      run_frame<scalar_t>(frame_args<scalar_t>(in), in.settings, -1, out0.mutable_data_ptr<scalar_t>(),
                          out1.mutable_data_ptr<scalar_t>(), nullptr, &ca);
    });
  }
  return {out0, out1};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> frame_finish_cpu(
    at::TensorList state, const std::optional<at::Tensor>& ext, at::TensorList model,
        at::TensorList poses AMS_FRAME_SETTINGS_PARAMS, bool hermite, int64_t assemble_substep,
    at::TensorList finish_pose) {
  constexpr const char* op = "ams_torch_cpu::frame_finish";
  const FrameInputs in = check_frame_inputs(op, state, ext, model, poses AMS_FRAME_SETTINGS_ARGS, hermite,
      assemble_substep);
  return frame_impl(op, in, &finish_pose);
}

std::tuple<at::Tensor, at::Tensor> finish_cpu(const at::Tensor& x, const at::Tensor& v, const at::Tensor& num_pinned,
                                              at::TensorList pose) {
  constexpr const char* op = "ams_torch_cpu::finish";
  FinishInputs in = check_finish_inputs(op, x, v, num_pinned, pose);
  TORCH_CHECK(in.x.device().is_cpu(), op, ": CPU tensors expected");
  const int64_t strands = in.scenes * in.strands, n = in.particles;
  if (strands > 0 && n > 0) {
    AT_DISPATCH_FLOATING_TYPES(in.x.scalar_type(), op, [&] {
      const FinishArgs<scalar_t> a = finish_args<scalar_t>(in);
      at::parallel_for(0, strands, std::max<int64_t>(1, 4096 / n), [&](int64_t begin, int64_t end) {
        for (int64_t g = begin; g < end; ++g) finish_range(a, g, 0, n);
      });
    });
  }
  return {in.v_out, in.speed};
}

} // namespace
} // namespace frame
} // namespace ams_torch

TORCH_LIBRARY_FRAGMENT(ams_torch_cpu, m) {
  m.def(ams_torch::frame::kFrameSchema);
  m.def(ams_torch::frame::kFrameFinishSchema);
  m.def(ams_torch::frame::kFinishSchema);
  m.def(ams_torch::frame::kFrameContactSchema);
}

TORCH_LIBRARY_IMPL(ams_torch_cpu, CPU, m) {
  m.impl("frame_contact", &ams_torch::frame::frame_contact_cpu);
  m.impl("frame", &ams_torch::frame::frame_cpu);
  m.impl("frame_finish", &ams_torch::frame::frame_finish_cpu);
  m.impl("finish", &ams_torch::frame::finish_cpu);
}
