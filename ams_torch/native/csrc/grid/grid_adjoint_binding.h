// The schemas of the grid's adjoint ops, shared by the CPU kernels (grid_adjoint_cpu.cpp) and the
// CUDA binding (grid_adjoint_cuda_binding.cpp); shapes there. Never included by CUDA sources.
#pragma once

namespace ams_torch {
namespace grid {

constexpr const char* kP2GAdjointSchema =
    "p2g_adjoint(Tensor xl, Tensor vl, Tensor m, Tensor origin, Tensor table, Tensor g_faces, float cell_size, "
    "int resolution) -> (Tensor, Tensor, Tensor)";
constexpr const char* kG2PAdjointSchema =
    "g2p_adjoint(Tensor xl, Tensor vl, Tensor field, Tensor table, Tensor origin, Tensor g_dv, float cell_size, "
    "int resolution, float pic) -> (Tensor, Tensor, Tensor, Tensor)";
constexpr const char* kPressureAdjointSchema =
    "pressure_adjoint(Tensor faces, Tensor table, Tensor blocks, Tensor count, Tensor target, Tensor dt, "
    "float cell_size, int resolution, int iterations, float omega, float stiffness, float pic, Tensor g_field) "
    "-> Tensor";

} // namespace grid
} // namespace ams_torch
