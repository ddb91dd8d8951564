"""Fixtures shared by the test packages."""

import pytest


@pytest.fixture(params=[pytest.param("array_api_strict"), pytest.param("cupy", marks=pytest.mark.gpu)])
def namespace_backend(request):
    """A backend other than NumPy for the engine (doedesign.engine.backend): array_api_strict, a
    namespace that refuses anything outside the array API standard, and CuPy where a GPU is
    usable (skipped elsewhere)."""
    from doedesign.engine import backend as be

    if request.param == "array_api_strict":
        return be.strict_backend()
    why = be.gpu_unavailable_reason()
    if why is not None:
        pytest.skip(f"no GPU: {why}")
    return be.select_backend("gpu")
