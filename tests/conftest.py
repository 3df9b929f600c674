import pytest
import torch

# Note: do not call torch.set_num_threads here. With the torch 2.13.0 CPU wheel (MKL
# 2024.2) an explicit set_num_threads(2) makes batched torch.linalg.solve on 768×768
# matrices spin forever printing "oneMKL ERROR: Parameter 6 was incorrect on entry to
# DLASWP" (seen on the 2-core CI machine; 1 thread or the default setting is fine).

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)
