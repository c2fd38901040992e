"""The runtimes that run the occupancy model's pass: one window of grid states in, logits out.

Two engines run the same trained weights (:class:`mapper.model.OccupancyNet`):

- ``openvino`` (the default): the network rebuilt as an OpenVINO graph from the checkpoint's
  tensors and compiled for this CPU, in float32. Two exact rewrites take work out of it.
  The input's five position channels and its constant channel are the same in every window,
  so the stem's response to them is computed once, in float64, as a volume added to the
  stem's output. The three state channels are one-hot (every voxel is occupied, free or
  unknown, never two), so ``unknown = 1 - occupied - free`` and the stem convolves two
  channels; the constant part goes into the same volume. The head's first 1x1 convolution is
  folded into the last transposed convolution before it, which removes the full-resolution
  12-channel volume and the concatenation.
  In real arithmetic this is the network; in float32 the sums run in another order, which
  moves logits by a few 1e-5 (see ``tests/test_occupancy_model.py``).
- ``torch``: the network as trained, in PyTorch, in float32 or bfloat16.

Why OpenVINO by default: PyTorch's CPU path runs five of the network's sixteen convolutions
(the dilated, the strided and the transposed ones) through generic kernels rather than
oneDNN's, and copies every concatenation; OpenVINO runs them all on oneDNN's JIT kernels for
the CPU at hand (AVX2, AVX-512, or NEON on aarch64).

Threads: an engine uses ``torch.get_num_threads()`` threads, so the one knob a study worker
sets (one thread each) holds for either runtime.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

import numpy as np
import torch

from mapper.grid import FREE, OCCUPIED
from rovergate.errors import ConfigError

#: The arithmetic the model may run in (``--mapper.precision``).
PRECISIONS = ("float32", "bfloat16")


class Engine(ABC):
    """Runs the occupancy model on one window.

    Contract: ``__call__`` takes an (X, Y, Z) uint8 state window of the size the checkpoint's
    :class:`mapper.model.WindowSpec` names (camera voxel at (X // 2, Y // 2, below)) and
    returns the (X, Y, Z) float32 surface logits; the same window gives the same logits to the
    bit on the same machine, whatever the number of threads.
    """

    name: str
    precision: str

    @abstractmethod
    def __call__(self, state: np.ndarray) -> np.ndarray: ...


class TorchEngine(Engine):
    """The network as trained, in PyTorch: float32, or bfloat16 (about 1.7 times faster on a CPU
    with native bfloat16, AVX512-BF16 or AMX; many times slower on one without)."""

    name = "torch"

    def __init__(self, checkpoint, precision: str = "float32") -> None:
        import copy

        from mapper.model import encode
        self.precision = precision
        self.dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16}[precision]
        self.model = (checkpoint.model if self.dtype == torch.float32
                      else copy.deepcopy(checkpoint.model).to(self.dtype))
        w = checkpoint.window
        # Channels 3.. (the position in the window) never change: written once.
        self._x = encode(np.zeros(w.size, dtype=np.uint8), w.below)

    @torch.inference_mode()
    def __call__(self, state: np.ndarray) -> np.ndarray:
        from mapper.model import encode_state
        self._x[:3] = encode_state(state)
        x = torch.from_numpy(self._x)[None].to(self.dtype)
        return self.model(x)[0, 0].to(torch.float32).numpy()


# ----------------------------------------------------------------------------- OpenVINO

def _f64(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy().astype(np.float64)


def stem_constant(checkpoint) -> np.ndarray:
    """(C0, X, Y, Z) float32: the stem's pre-activation response to everything in its input that
    is the same in every window: the position and constant channels, the bias, and the unknown
    channel's weights applied to a window of ones (``unknown = 1 - occupied - free``), with the
    convolution's zero padding at the window's edges. Computed in float64 and rounded once, so
    the volume is the same on every CPU."""
    from mapper.model import encode
    w = checkpoint.window
    x = encode(np.zeros(w.size, dtype=np.uint8), w.below).astype(np.float64)  # unknown: all 1
    stem = checkpoint.model.stem[0]
    out = torch.nn.functional.conv3d(torch.from_numpy(x[2:])[None],
                                     torch.from_numpy(_f64(stem.weight[:, 2:])),
                                     torch.from_numpy(_f64(stem.bias)), padding=1)
    return out[0].numpy().astype(np.float32)


def build_openvino_graph(checkpoint):
    """The network as an ``openvino.Model`` with the two rewrites of this module's docstring:
    input (1, 2, X, Y, Z) float32 (occupied, free), output (1, 1, X, Y, Z) logits."""
    import openvino as ov
    import openvino.opset13 as op

    net = checkpoint.model
    sd = {k: _f64(v) for k, v in net.state_dict().items()}

    def f32(a: np.ndarray):
        return op.constant(np.ascontiguousarray(a, dtype=np.float32))

    def bias(b: np.ndarray):
        return f32(b.reshape(1, -1, 1, 1, 1))

    def conv(x, name: str, stride: int = 1, dilation: int = 1, relu: bool = True):
        wt = sd[f"{name}.weight"]
        pad = 0 if stride > 1 else dilation * (wt.shape[-1] // 2)
        y = op.convolution(x, f32(wt), [stride] * 3, [pad] * 3, [pad] * 3, [dilation] * 3)
        y = op.add(y, bias(sd[f"{name}.bias"]))
        return op.relu(y) if relu else y

    def up(x, weight: np.ndarray, b: np.ndarray):
        y = op.convolution_backprop_data(x, f32(weight), [2] * 3, pads_begin=[0] * 3,
                                         pads_end=[0] * 3, dilations=[1] * 3)
        return op.add(y, bias(b))

    w = checkpoint.window
    x = op.parameter([1, 2, *w.size], np.float32, name="occupied_free")
    ws = sd["stem.0.weight"]
    # occupied and free, each against unknown (their weights less the unknown channel's).
    w_state = np.stack([ws[:, 0] - ws[:, 2], ws[:, 1] - ws[:, 2]], axis=1)
    f0 = op.relu(op.add(op.convolution(x, f32(w_state), [1] * 3, [1] * 3, [1] * 3, [1] * 3),
                        op.constant(stem_constant(checkpoint)[None])))
    f1 = conv(conv(f0, "down1.0.0", stride=2), "down1.1.0")
    f2 = conv(conv(conv(f1, "down2.0.0", stride=2), "down2.1.0"), "down2.2.0", dilation=2)
    f3 = conv(conv(conv(f2, "down3.0.0", stride=2), "down3.1.0"), "down3.2.0", dilation=2)
    g2 = conv(op.concat([up(f3, sd["up3.weight"], sd["up3.bias"]), f2], 1), "fuse2.0")
    g1 = conv(op.concat([up(g2, sd["up2.weight"], sd["up2.bias"]), f1], 1), "fuse1.0")
    # head.0 (1x1) of [up1(g1), f0] = (head.0's first half) o up1, applied to g1, plus its
    # second half applied to f0: one transposed convolution and one 1x1 convolution.
    wh, bh = sd["head.0.0.weight"][:, :, 0, 0, 0], sd["head.0.0.bias"]
    c0 = sd["up1.weight"].shape[1]
    w_up = np.einsum("ioxyz,ho->ihxyz", sd["up1.weight"], wh[:, :c0])
    b_up = wh[:, :c0] @ sd["up1.bias"] + bh
    h = op.add(up(g1, w_up, b_up),
               op.convolution(f0, f32(wh[:, c0:, None, None, None]), [1] * 3, [0] * 3,
                              [0] * 3, [1] * 3))
    logits = conv(op.relu(h), "head.1", relu=False)
    return ov.Model([logits], [x], "occupancy")


class OpenVinoEngine(Engine):
    """The network compiled by OpenVINO for this CPU (see the module's docstring)."""

    name = "openvino"

    def __init__(self, checkpoint, precision: str = "float32") -> None:
        try:
            import openvino as ov
        except ImportError as e:
            raise ConfigError(f"--mapper.engine openvino needs the openvino package ({e}); "
                              "install it (pip install openvino) or use --mapper.engine "
                              "torch") from None
        refusal = ConfigError("--mapper.precision bfloat16 with --mapper.engine openvino needs a "
                              "CPU with native bfloat16 (AVX512-BF16 or AMX), and this one has "
                              "none; use --mapper.precision float32")
        core = ov.Core()
        if precision == "bfloat16" and "BF16" not in core.get_property(
                "CPU", "OPTIMIZATION_CAPABILITIES"):
            raise refusal
        self.precision = precision
        try:
            # The precision is named: on a CPU with native bfloat16, OpenVINO would otherwise
            # choose bfloat16 by itself.
            self._compiled = core.compile_model(build_openvino_graph(checkpoint), "CPU", {
                "INFERENCE_PRECISION_HINT": {"float32": "f32", "bfloat16": "bf16"}[precision],
                "INFERENCE_NUM_THREADS": torch.get_num_threads(),
                "NUM_STREAMS": 1,
                "PERFORMANCE_HINT": "LATENCY",
            })
        except RuntimeError:
            # A CPU whose bfloat16 OpenVINO reports but oneDNN may not use (an instruction
            # set capped by ONEDNN_MAX_CPU_ISA) has no bfloat16 kernel for the transposed
            # convolutions.
            if precision == "bfloat16":
                raise refusal from None
            raise
        self._request = self._compiled.create_infer_request()
        self._x = np.zeros((1, 2, *checkpoint.window.size), dtype=np.float32)

    def kernels(self) -> set[str]:
        """The kernels OpenVINO chose for this CPU (``brgconv_avx512_f32``, ``jit_avx2_f32``,
        ...): which instruction set its pass really runs on."""
        return {op.get_rt_info()["primitiveType"].astype(str)
                for op in self._compiled.get_runtime_model().get_ops()
                if "primitiveType" in op.get_rt_info()}

    def __call__(self, state: np.ndarray) -> np.ndarray:
        np.not_equal(state & OCCUPIED, 0, out=self._x[0, 0])  # bool into float32: 0 or 1
        np.equal(state, FREE, out=self._x[0, 1])
        self._request.infer({0: self._x})
        return self._request.get_output_tensor(0).data[0, 0].copy()


ENGINES: dict[str, Callable[..., Engine]] = {"openvino": OpenVinoEngine, "torch": TorchEngine}


def make_engine(checkpoint, name: str = "openvino", precision: str = "float32") -> Engine:
    """The engine ``name`` for ``checkpoint`` in ``precision``; an unknown name or precision
    raises ConfigError naming the valid ones."""
    if name not in ENGINES:
        raise ConfigError(f"--mapper.engine {name!r} is not an engine; choose one of: "
                          f"{', '.join(ENGINES)}")
    if precision not in PRECISIONS:
        raise ConfigError(f"--mapper.precision {precision!r} is not one of "
                          f"{', '.join(PRECISIONS)}")
    return ENGINES[name](checkpoint, precision)
