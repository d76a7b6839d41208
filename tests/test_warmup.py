"""`make venv` compiles the numba kernels with `collabslam.warmup`: a kernel whose
signature changed had left its warm-up (and the ones after it) silently undone."""

from __future__ import annotations

import pytest

from collabslam import warmup


def test_the_warmup_calls_every_kernel_as_it_is(capsys: pytest.CaptureFixture[str]) -> None:
    warmup.main()
    assert "numba kernels compiled" in capsys.readouterr().out
