// CUDA emulation (ams_torch/native/csrc/emulation): stands in for the toolkit's header.
#pragma once
#include "cuda_emulation.h"
