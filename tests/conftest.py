import pytest
import torch

# One intra-op thread for the whole suite. Two reasons, both measured on the 2-core CI kind:
# - with the torch 2.13.0 CPU wheel (MKL 2024.2), an explicit torch.set_num_threads(2) makes
#   batched torch.linalg.solve/lu on 768×768 matrices spin forever printing "oneMKL ERROR:
#   Parameter 6 was incorrect on entry to DLASWP" (1 thread, or never calling it, is fine);
# - the tests' tensors are small, so a second thread mostly waits (up to 15× slower under load).
torch.set_num_threads(1)

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)
