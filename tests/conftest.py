import pytest
import torch

# One intra-op thread for the whole suite. Two reasons, both measured on the 2-core CI kind:
# - with the torch 2.13.0 CPU wheel (MKL 2024.2), an explicit torch.set_num_threads(2) makes
#   batched torch.linalg.solve/lu on 768×768 matrices spin forever printing "oneMKL ERROR:
#   Parameter 6 was incorrect on entry to DLASWP" (1 thread, or never calling it, is fine);
# - the tests' tensors are small, so a second thread mostly waits (up to 15× slower under load).
torch.set_num_threads(1)

from helpers import DEVICES, built_native  # noqa: E402  (after the thread count is set)


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


@pytest.fixture(scope="session")
def head():
    """The default head mesh (``ams_torch.default_head()``), once per session."""
    from ams_torch.grooms.head import default_head

    return default_head()


@pytest.fixture(scope="session")
def head_sdf(head, tmp_path_factory):
    """The default head's 64³ signed-distance grid, built once per session."""
    from ams_torch.geometry.sdf import SDFGrid

    return SDFGrid.from_mesh(head, resolution=64, cache_dir=tmp_path_factory.mktemp("sdf"))


@pytest.fixture(scope="session")
def cpu_ops():
    """The CPU native library (every op group's kernels: ``ams_torch_cpu``), built or loaded once
    per session (skips as ``built_native``)."""
    return built_native("cpu")
