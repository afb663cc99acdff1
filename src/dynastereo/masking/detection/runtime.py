"""The inference runtime of an ONNX detector: onnxruntime or OpenVINO, and its precision.

``detector.runtime``: ``onnxruntime`` (always installed), ``openvino`` (the optional extra
``pip install 'dynastereo[openvino]'``) or ``auto`` (OpenVINO in bf16 when it is installed
and the CPU computes in bf16, else onnxruntime f32: OpenVINO's f32 costs more CPU than
onnxruntime's on the measured machine, ``benchmarks/bench_detect.py --runtimes``).  ``detector.precision``: ``auto`` (bf16 on a CPU that computes in bf16 --
OpenVINO's ``OPTIMIZATION_CAPABILITIES`` lists ``BF16``: AVX512-BF16 / AMX x86, some ARM
-- f32 elsewhere and always on onnxruntime), ``f32`` or ``bf16`` (OpenVINO only; on a CPU
without it: f32 with one line saying so).  Asking for OpenVINO where it is not installed
falls back to onnxruntime with ONE logged line (``auto`` too: the extra is what makes the
detector cheapest where the CPU has bf16).

Both runtimes are set up alike for a two-core machine that also runs the tracking: a
fixed number of inference threads (``detector.threads``), one stream, no busy-waiting
between calls (onnxruntime: ``allow_spinning 0``; OpenVINO: a latency hint, one stream,
no CPU pinning), so the process time of a call is about its wall time times the threads
it really uses.  The session objects share one small interface (``get_inputs``,
``get_outputs``, ``get_modelmeta``, ``run``) so the detectors do not know which runs them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...config import DETECTOR_PRECISIONS, DETECTOR_RUNTIMES
from ...errors import ModelError

log = logging.getLogger("dynastereo.detector")

RUNTIMES = DETECTOR_RUNTIMES
PRECISIONS = DETECTOR_PRECISIONS


def openvino_available() -> bool:
    try:
        import openvino  # noqa: F401
    except Exception:  # ImportError, or a broken install (missing shared library)
        return False
    return True


_CAPS: dict[str, tuple[str, ...]] = {}


def cpu_capabilities() -> tuple[str, ...]:
    """OpenVINO's ``OPTIMIZATION_CAPABILITIES`` of the CPU (``()`` without OpenVINO)."""
    if "cpu" not in _CAPS:
        try:
            import openvino as ov

            _CAPS["cpu"] = tuple(str(c) for c in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES"))
        except Exception:
            _CAPS["cpu"] = ()
    return _CAPS["cpu"]


@dataclass(frozen=True)
class RuntimeChoice:
    """What actually runs: ``runtime`` (onnxruntime | openvino), ``precision`` (f32 | bf16)
    and, when it differs from the request, why (``note``)."""

    runtime: str
    precision: str
    note: str = ""

    @property
    def label(self) -> str:
        return f"{self.runtime}/{self.precision}"


_NOTED: set[str] = set()


def _note_once(msg: str) -> None:
    if msg and msg not in _NOTED:
        _NOTED.add(msg)
        log.warning(msg)


def resolve_runtime(runtime: str = "auto", precision: str = "auto", *, have_openvino: bool | None = None,
                    caps: tuple[str, ...] | None = None) -> RuntimeChoice:
    """The runtime and precision for a request (module docstring); logs the one-line
    fallback message when the request cannot be met (once per message and process)."""
    if runtime not in RUNTIMES:
        raise ModelError(f"detector.runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r}")
    if precision not in PRECISIONS:
        raise ModelError(f"detector.precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    have = openvino_available() if have_openvino is None else have_openvino
    note = ""
    rt = runtime
    if runtime == "auto" and have and precision != "f32":
        # OpenVINO only where it computes in bf16: its f32 costs 1.3-1.5x onnxruntime's CPU
        # (benchmarks/bench_detect.py --runtimes)
        caps = cpu_capabilities() if caps is None else caps
        if "BF16" not in caps:
            return _finish(RuntimeChoice("onnxruntime", "f32", ""))
    elif runtime == "auto" and precision == "f32":
        return _finish(RuntimeChoice("onnxruntime", "f32", ""))
    if runtime in ("auto", "openvino"):
        if have:
            rt = "openvino"
        else:
            rt = "onnxruntime"
            note = (f"detector.runtime {runtime}: OpenVINO is not installed (pip install 'dynastereo[openvino]'); "
                    "running the detector on onnxruntime")
    if rt == "onnxruntime":
        if precision == "bf16":
            note = note or "detector.precision bf16 needs the OpenVINO runtime; running f32 on onnxruntime"
        return _finish(RuntimeChoice("onnxruntime", "f32", note))
    caps = cpu_capabilities() if caps is None else caps
    bf16 = "BF16" in caps
    if precision == "bf16" and not bf16:
        return _finish(RuntimeChoice("openvino", "f32", "detector.precision bf16: this CPU has no bf16 arithmetic "
                                     "(OpenVINO capabilities: " + ", ".join(caps) + "); running f32"))
    if precision == "auto":
        return _finish(RuntimeChoice("openvino", "bf16" if bf16 else "f32", note))
    return _finish(RuntimeChoice("openvino", precision, note))


def _finish(c: RuntimeChoice) -> RuntimeChoice:
    _note_once(c.note)
    return c


# ------------------------------------------------------------------ OpenVINO session


@dataclass(frozen=True)
class _Port:
    name: str
    shape: list[Any]


class _Meta:
    def __init__(self, m: dict[str, str]):
        self.custom_metadata_map = m


def _onnx_metadata(path: Path, model_bytes: bytes | None) -> dict[str, str]:
    try:
        import onnx

        m = onnx.load_from_string(model_bytes) if model_bytes is not None else onnx.load(str(path), load_external_data=False)
        return {p.key: p.value for p in m.metadata_props}
    except Exception:
        return {}


class OpenVinoSession:
    """An ONNX graph compiled by OpenVINO for the CPU, with onnxruntime's session
    interface (the parts the detectors use)."""

    def __init__(self, path: Path, threads: int, precision: str = "f32", model_bytes: bytes | None = None):
        import openvino as ov

        if model_bytes is None and not Path(path).is_file():
            raise ModelError("ONNX model file not found", path)
        core = ov.Core()
        try:
            if model_bytes is not None:
                model = core.read_model(model=model_bytes, weights=b"")
            else:
                model = core.read_model(str(path))
        except Exception as e:
            raise ModelError(f"OpenVINO cannot read the model: {e}", path) from None
        cfg = {
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": "1",
            "INFERENCE_NUM_THREADS": str(max(1, int(threads))),
            "ENABLE_CPU_PINNING": "NO",
            "INFERENCE_PRECISION_HINT": "bf16" if precision == "bf16" else "f32",
        }
        try:
            self.compiled = core.compile_model(model, "CPU", cfg)
        except Exception as e:
            raise ModelError(f"OpenVINO cannot compile the model for the CPU: {e}", path) from None
        self.request = self.compiled.create_infer_request()
        self.precision = precision
        self._inputs = [_Port(p.any_name, [d.get_length() if d.is_static else None for d in p.get_partial_shape()])
                        for p in self.compiled.inputs]
        self._outputs = [_Port(p.any_name, [d.get_length() if d.is_static else None for d in p.get_partial_shape()])
                         for p in self.compiled.outputs]
        self._meta = _Meta(_onnx_metadata(Path(path), model_bytes))

    def get_inputs(self) -> list[_Port]:
        return self._inputs

    def get_outputs(self) -> list[_Port]:
        return self._outputs

    def get_modelmeta(self) -> _Meta:
        return self._meta

    def run(self, _names: Any, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        res = self.request.infer(feed)
        return [np.array(res[o]) for o in self.compiled.outputs]  # copies: the request reuses its buffers
