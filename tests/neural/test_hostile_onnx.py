"""Hostile ONNX predictor files and hostile conditions around ``export-onnx`` (issue 23).

Each file here is built with ``onnx.helper`` to look like a macsplat predictor (inputs ``img0``/``img1``,
the four outputs, readable metadata) and to attack one thing: control flow that never ends, custom
operators, subgraphs, metadata of the wrong type or range, an allocation bomb inside the forward,
outputs of the wrong shape, weights read from outside the model's folder, a run that would hold the
process past SIGTERM/Ctrl-C. Every one must end in one line on stderr and exit code 2 (130/143 for a
signal), with no output file. ``export-onnx`` must report a folder it cannot write (``/sys`` as root, a
full disk) the same way.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper

from macsplat_cli.datasets.synthetic.sample import sample_pair
from macsplat_cli.errors import InputError, OutputPathError
from macsplat_cli.neural import BackboneView, MASt3RBackbone
from macsplat_cli.neural.config import BackboneConfig
from macsplat_cli.neural.onnx_export import ExportConfig, export_onnx
from macsplat_cli.neural.onnx_format import METADATA_KEY, OnnxPredictorError, OnnxPredictorInfo
from macsplat_cli.neural.onnx_runtime import OnnxPairPredictor
from macsplat_cli.neural.predictor import PairPredictor
from macsplat_cli.neural.predictor_io import save_predictor_checkpoint

from support import REPO
from support.cli import file_size_limit, one_error_line, run_cli
from support.scenes import PairFactory, PairSpec

SIZE = (96, 64)  # (W, H) of the photos, multiples of 16
FOUR = ("pts3d", "conf", "desc", "desc_conf")
STOP_WITHIN_S = 8.0
"""A signalled run must have ended this long after the signal (onnxruntime stops between two nodes; one
node of the slow graph below takes well under a second)."""


# ------------------------------------------------------------------------------ helpers


def _metadata(**changes: object) -> str:
    """A valid ``macsplat.predictor`` metadata string (dynamic, fp32, no Gaussian head), with ``changes``."""
    info = OnnxPredictorInfo(
        precision="fp32", dynamic=True, size=SIZE, network="hostile", fusion="none", fusion_enabled=False,
        desc_dim=24, gaussian_head=False,
    )  # fmt: skip
    doc = json.loads(info.to_json())
    doc.update(changes)
    return json.dumps(doc)


def _tail(outputs_from: str = "img0") -> list[onnx.NodeProto]:
    """Nodes of allowed operators giving the four outputs (not of the right shapes) from ``outputs_from``."""
    return [
        helper.make_node("Add", [outputs_from, "img1"], ["pts3d"]),
        helper.make_node("Mul", ["img0", "img1"], ["conf"]),
        helper.make_node("Sub", ["img0", "img1"], ["desc"]),
        helper.make_node("Div", ["img0", "img1"], ["desc_conf"]),
    ]


def _model(
    nodes: list[onnx.NodeProto],
    initializers: list[onnx.TensorProto] | None = None,
    *,
    metadata: str | None = None,
    opsets: list[onnx.OperatorSetIdProto] | None = None,
) -> onnx.ModelProto:
    """A graph shaped like a macsplat predictor: float ``img0``, ``img1`` ``[b, 3, h, w]`` in, the four outputs out."""
    ins = [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["b", 3, "h", "w"]) for n in ("img0", "img1")]
    outs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in FOUR]
    graph = helper.make_graph(nodes, "hostile", ins, outs, initializer=initializers or [])
    model = helper.make_model(graph, opset_imports=opsets or [helper.make_opsetid("", 18)])
    model.metadata_props.add(key=METADATA_KEY, value=metadata if metadata is not None else _metadata())
    return model


def _save(model: onnx.ModelProto, path: Path) -> Path:
    path.write_bytes(model.SerializeToString())
    return path


def _int64(name: str, values: list[int]) -> onnx.TensorProto:
    return helper.make_tensor(name, TensorProto.INT64, [len(values)], values)


def _slow_graph(path: Path, size: int = 2048, steps: int = 1000) -> Path:
    """Allowed operators only, and minutes of work: a ``size``² matrix (from the input, so nothing folds at load)
    squared ``steps`` times. One step is a few hundred milliseconds on two cores."""
    nodes = [
        helper.make_node("ReduceL2", ["img0"], ["m"], keepdims=0),
        helper.make_node("Expand", ["m", "square"], ["a0"]),
    ]
    nodes += [helper.make_node("MatMul", [f"a{i}", f"a{i}"], [f"a{i + 1}"]) for i in range(steps)]
    return _save(_model(nodes + _tail(f"a{steps}"), [_int64("square", [size, size])]), path)


def _folding_graph(path: Path, size: int = 2048, steps: int = 2000) -> Path:
    """The same work on constants only: onnxruntime's constant folding does it while it creates the session."""
    nodes = [helper.make_node("Expand", ["one", "square"], ["a0"])]
    nodes += [helper.make_node("MatMul", [f"a{i}", f"a{i}"], [f"a{i + 1}"]) for i in range(steps)]
    inits = [helper.make_tensor("one", TensorProto.FLOAT, [1], [1e-3]), _int64("square", [size, size])]
    return _save(_model(nodes + _tail(f"a{steps}"), inits), path)


def _bomb_graph(path: Path) -> Path:
    """An allocation bomb of allowed operators: ``Expand`` to ``[2²⁰·B]³`` floats (4 EiB), the size computed from
    the input so that onnxruntime cannot fold it when it loads the file."""
    nodes = [
        helper.make_node("Shape", ["img0"], ["batch"], start=0, end=1),
        helper.make_node("Mul", ["batch", "huge"], ["shape"]),
        helper.make_node("Expand", ["one", "shape"], ["x"]),
        *_tail("x"),
    ]
    inits = [_int64("huge", [1 << 20] * 3), helper.make_tensor("one", TensorProto.FLOAT, [1], [1.0])]
    return _save(_model(nodes, inits), path)


@pytest.fixture(scope="module")
def pair(pair_files: PairFactory) -> tuple[Path, Path]:
    """A textured room pair 20° apart, 50° field of view, at ``SIZE``."""
    return pair_files(PairSpec("room", 20.0, SIZE, fov_deg=50.0)).photos


@pytest.fixture
def no_session(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any onnxruntime session created while the test runs fails it: the file must be refused before."""
    import onnxruntime

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("onnxruntime was given the file")

    monkeypatch.setattr(onnxruntime, "InferenceSession", refuse)


def _reconstruct(pair: tuple[Path, Path], weights: Path, out: Path, *extra: str) -> tuple[int, str, str]:
    return run_cli(["reconstruct", *pair, "-o", out, "--backend", "neural", "--weights", weights, *extra])


# ------------------------------------------------------------------------------ operators
def _loop() -> onnx.ModelProto:
    body = helper.make_graph(
        [helper.make_node("Identity", ["cond_in"], ["cond_out"]), helper.make_node("Add", ["x_in", "x_in"], ["x_out"])],
        "body",
        [helper.make_tensor_value_info("i", TensorProto.INT64, []),
         helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
         helper.make_tensor_value_info("x_in", TensorProto.FLOAT, None)],
        [helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
         helper.make_tensor_value_info("x_out", TensorProto.FLOAT, None)],
    )  # fmt: skip
    nodes = [helper.make_node("Loop", ["trips", "true", "img0"], ["x"], body=body), *_tail("x")]
    inits = [helper.make_tensor("trips", TensorProto.INT64, [], [1 << 62]),
             helper.make_tensor("true", TensorProto.BOOL, [], [True])]  # fmt: skip
    return _model(nodes, inits)


def _if() -> onnx.ModelProto:
    def branch(name: str) -> onnx.GraphProto:
        return helper.make_graph([helper.make_node("Neg", ["img0"], [f"y_{name}"])], name, [],
                                 [helper.make_tensor_value_info(f"y_{name}", TensorProto.FLOAT, None)])  # fmt: skip

    nodes = [
        helper.make_node("ReduceL2", ["img0"], ["m"], keepdims=0),
        helper.make_node("Greater", ["m", "zero"], ["c"]),
        helper.make_node("If", ["c"], ["x"], then_branch=branch("then"), else_branch=branch("else")),
        *_tail("x"),
    ]
    return _model(nodes, [helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0])])


def _scan() -> onnx.ModelProto:
    body = helper.make_graph(
        [helper.make_node("Add", ["s_in", "row"], ["s_out"]), helper.make_node("Neg", ["row"], ["row_out"])],
        "body",
        [helper.make_tensor_value_info("s_in", TensorProto.FLOAT, None),
         helper.make_tensor_value_info("row", TensorProto.FLOAT, None)],
        [helper.make_tensor_value_info("s_out", TensorProto.FLOAT, None),
         helper.make_tensor_value_info("row_out", TensorProto.FLOAT, None)],
    )  # fmt: skip
    nodes = [helper.make_node("Scan", ["img1", "img0"], ["s", "x"], body=body, num_scan_inputs=1), *_tail("x")]
    return _model(nodes)


def _custom_domain() -> onnx.ModelProto:
    nodes = [helper.make_node("Pwn", ["img0"], ["x"], domain="com.evil"), *_tail("x")]
    return _model(nodes, opsets=[helper.make_opsetid("", 18), helper.make_opsetid("com.evil", 1)])


def _subgraph_attribute() -> onnx.ModelProto:
    """An allowed operator carrying a graph attribute (which onnxruntime would ignore, or worse)."""
    payload = helper.make_graph([helper.make_node("Neg", ["img0"], ["y"])], "payload", [],
                                [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)])  # fmt: skip
    node = helper.make_node("Add", ["img0", "img1"], ["x"])
    node.attribute.append(helper.make_attribute("payload", payload))
    return _model([node, *_tail("x")])


def _local_function() -> onnx.ModelProto:
    fn = helper.make_function("local", "Twice", ["a"], ["b"], [helper.make_node("Add", ["a", "a"], ["b"])],
                              [helper.make_opsetid("", 18)])  # fmt: skip
    model = _model([helper.make_node("Twice", ["img0"], ["x"], domain="local"), *_tail("x")],
                   opsets=[helper.make_opsetid("", 18), helper.make_opsetid("local", 1)])  # fmt: skip
    model.functions.append(fn)
    return model


@pytest.mark.parametrize(
    ("build", "message"),
    [
        pytest.param(_loop, "operators export-onnx never writes (Loop)", id="loop-2^62"),
        pytest.param(_if, "operators export-onnx never writes (If)", id="if"),
        pytest.param(_scan, "operators export-onnx never writes (Scan)", id="scan"),
        pytest.param(_custom_domain, "never writes (com.evil:Pwn)", id="custom-domain"),
        pytest.param(_subgraph_attribute, "carries a subgraph in its attribute 'payload'", id="graph-attribute"),
        pytest.param(_local_function, "defines its own ONNX functions (local:Twice)", id="local-function"),
    ],
)
def test_operators_the_exporter_never_writes_are_refused_before_onnxruntime_sees_them(
    build,
    message: str,
    pair: tuple[Path, Path],
    tmp_path: Path,
    no_session: None,  # noqa: ANN001
) -> None:
    """A ``Loop`` of 2⁶² iterations would hold the process (onnxruntime's ``run`` keeps the thread): nothing
    outside what the exporter writes reaches onnxruntime."""
    path = _save(build(), tmp_path / "hostile.onnx")
    with pytest.raises(OnnxPredictorError, match=message.replace("(", r"\(").replace(")", r"\)")):
        OnnxPairPredictor(path)
    code, _, err = _reconstruct(pair, path, tmp_path / "s.ply")
    assert code == 2 and message in one_error_line(err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hostile.onnx"]


# ------------------------------------------------------------------------------ metadata
@pytest.mark.parametrize(
    ("changes", "field"),
    [
        pytest.param({"size": [0, 0], "dynamic": False}, "'size'", id="size-0"),
        pytest.param({"size": [-16, -16], "dynamic": False}, "'size'", id="size-negative"),
        pytest.param({"size": [1e9, 1e9], "dynamic": False}, "'size'", id="size-1e9-float"),
        pytest.param({"size": [1 << 30, 1 << 30], "dynamic": False}, "'size'", id="size-2^30"),
        pytest.param({"size": [100, 64], "dynamic": False}, "'size'", id="size-not-16k"),
        pytest.param({"config": "a string"}, "'config'", id="config-string"),
        pytest.param({"config": {"backbone": {"img_size": 224}}}, "'config.backbone'", id="img-size-int"),
        pytest.param({"dynamic": "false"}, "'dynamic'", id="dynamic-string"),
        pytest.param({"desc_dim": 0}, "'desc_dim'", id="desc-dim-0"),
        pytest.param(
            {"fusion_enabled": True, "dino": {"name": "x", "patch_size": 0, "embed_dim": 8}},
            "'dino'",
            id="dino-patch-0",
        ),  # fmt: skip
        pytest.param({"network": {"x": 1}}, "'network'", id="network-object"),
        pytest.param({"sources": ["x"]}, "'sources'", id="sources-list"),
    ],
)
def test_metadata_of_the_wrong_type_or_range_is_exit_2_naming_the_field(
    changes: dict, field: str, pair: tuple[Path, Path], tmp_path: Path
) -> None:
    path = _save(_model(_tail(), metadata=_metadata(**changes)), tmp_path / "meta.onnx")
    code, _, err = _reconstruct(pair, path, tmp_path / "s.ply")
    line = one_error_line(err)
    assert code == 2 and f"metadata field {field}" in line, err
    assert not (tmp_path / "s.ply").exists()


def test_metadata_over_its_size_cap_is_refused(tmp_path: Path) -> None:
    path = _save(_model(_tail(), metadata=_metadata(network="n" * 2_000_000)), tmp_path / "big.onnx")
    with pytest.raises(OnnxPredictorError, match="characters"):
        OnnxPairPredictor(path)


# ------------------------------------------------------------------------------ the forward
def test_an_allocation_bomb_in_the_forward_is_exit_2(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """``Expand`` (an allowed operator) asked for 4 EiB: onnxruntime's Fail becomes one line, exit 2."""
    path = _bomb_graph(tmp_path / "bomb.onnx")
    predictor = OnnxPairPredictor(path)
    with pytest.raises(OnnxPredictorError, match="the model failed to run: .*Expand"):
        predictor(torch.rand(1, 3, 64, 96), torch.rand(1, 3, 64, 96))
    code, _, err = _reconstruct(pair, path, tmp_path / "s.ply")
    assert code == 2 and "the model failed to run" in one_error_line(err), err
    assert not (tmp_path / "s.ply").exists()


def test_outputs_of_the_wrong_shape_are_exit_2(pair: tuple[Path, Path], tmp_path: Path) -> None:
    path = _save(_model(_tail()), tmp_path / "shapes.onnx")
    code, _, err = _reconstruct(pair, path, tmp_path / "s.ply")
    assert code == 2 and "its output pts3d has shape [1, 3, 64, 96], expected [1, 2, 64, 96, 3]" in one_error_line(err)
    assert not (tmp_path / "s.ply").exists()


def _cli(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "macsplat_cli", *(str(a) for a in args)]


def _env() -> dict[str, str]:
    return {**os.environ, "NO_COLOR": "1", "COLUMNS": "200", "PYTHONPATH": str(REPO)}


def test_a_model_that_fails_prints_exactly_one_line(pair: tuple[Path, Path], tmp_path: Path) -> None:
    """onnxruntime's own (coloured) ERROR log would come before macsplat's line: it is silenced."""
    path = _bomb_graph(tmp_path / "bomb.onnx")
    proc = subprocess.run(
        _cli("reconstruct", *pair, "-o", tmp_path / "s.ply", "--backend", "neural", "--weights", path, "-q"),
        capture_output=True, text=True, env=_env(), timeout=300, cwd=tmp_path,
    )  # fmt: skip
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: the model failed to run"), (
        proc.stderr
    )
    assert not (tmp_path / "s.ply").exists()


# ------------------------------------------------------------------------------ signals
@pytest.mark.parametrize(
    ("stage", "build", "marker"),
    [
        pytest.param("run", _slow_graph, "onnxruntime run of run.onnx started", id="run"),
        pytest.param("load", _folding_graph, "onnxruntime loads load.onnx", id="load-constant-folding"),
    ],
)
def test_sigterm_ends_a_long_onnxruntime_call_within_seconds(
    stage: str,
    build,
    marker: str,
    pair: tuple[Path, Path],
    tmp_path: Path,  # noqa: ANN001
) -> None:
    """onnxruntime's ``run`` and its session creation (constant folding) hold the thread that calls them: they
    happen in a worker thread, and the signal, handled in the main thread, ends the wait (and tells a run to
    terminate). Exit 143 within seconds, no output."""
    path = build(tmp_path / f"{stage}.onnx")
    out = tmp_path / "out"
    proc = subprocess.Popen(
        _cli("reconstruct", *pair, "-o", out / "s.ply", "--backend", "neural", "--weights", path, "-v"),
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=_env(), cwd=tmp_path,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    stderr = proc.stderr
    assert stderr is not None
    threading.Thread(target=lambda: [lines.put(ln) for ln in stderr], daemon=True).start()
    seen: list[str] = []
    try:
        deadline = time.monotonic() + 60
        while not any(marker in ln for ln in seen):
            assert proc.poll() is None and time.monotonic() < deadline, "".join(seen)
            with contextlib.suppress(queue.Empty):
                seen.append(lines.get(timeout=0.5))
        time.sleep(1.0)  # well into the call
        assert proc.poll() is None, "".join(seen)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=STOP_WITHIN_S)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == 143 and took < STOP_WITHIN_S, (code, took)
    assert not out.exists() or list(out.iterdir()) == []


def test_ctrl_c_ends_a_long_run_in_the_library(tmp_path: Path) -> None:
    """SIGINT in the middle of :class:`OnnxPairPredictor`'s run: KeyboardInterrupt within seconds."""
    predictor = OnnxPairPredictor(_slow_graph(tmp_path / "slow.onnx"))
    running = threading.Event()
    done = threading.Event()

    def interrupt() -> None:
        if running.wait(30) and not done.wait(1.5):
            os.kill(os.getpid(), signal.SIGINT)

    timer = threading.Thread(target=interrupt, daemon=True)
    # Ctrl-C's handler, whatever started pytest (a background ``cmd &`` starts it with SIGINT ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer.start()
    t0 = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            running.set()
            predictor(torch.rand(1, 3, 64, 96), torch.rand(1, 3, 64, 96))
    finally:
        done.set()
        timer.join()
        signal.signal(signal.SIGINT, previous)
    assert time.monotonic() - t0 < 1.5 + STOP_WITHIN_S


# ------------------------------------------------------------------------------ external data
def _external_weights(folder: Path, location: str, length: int = 4) -> Path:
    """A predictor-shaped file whose one weight is stored externally at ``location``."""
    w = helper.make_tensor("w", TensorProto.FLOAT, [1], [0.0])
    w.ClearField("float_data")
    w.data_location = TensorProto.EXTERNAL
    for key, value in (("location", location), ("offset", "0"), ("length", str(length))):
        entry = w.external_data.add()
        entry.key, entry.value = key, value
    nodes = [helper.make_node("Add", ["img0", "w"], ["x"]), *_tail("x")]
    return _save(_model(nodes, [w]), folder / "ext.onnx")


@pytest.mark.parametrize(
    ("location", "message"),
    [
        pytest.param("../secret.bin", "outside the model's folder", id="dot-dot"),
        pytest.param("{secret}", "outside the model's folder", id="absolute"),
        pytest.param("link.bin", "outside the model's folder", id="symlink-out"),
        pytest.param("missing.bin", "not a file beside it", id="missing"),
        pytest.param("big", "past the end of that file", id="past-the-end"),
    ],
)
def test_external_weights_outside_the_model_folder_are_refused(
    location: str, message: str, tmp_path: Path, no_session: None
) -> None:
    """The weights of a file are read from beside it only (a link planted in an archive could point at any file)."""
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(4, dtype=np.float32).tobytes())
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "link.bin").symlink_to(secret)
    (folder / "big").write_bytes(b"\0" * 4)
    path = _external_weights(folder, location.format(secret=secret), length=8 if location == "big" else 4)
    with pytest.raises(OnnxPredictorError, match=message):
        OnnxPairPredictor(path)


# ------------------------------------------------------------------------------ export-onnx write failures
def test_export_onnx_into_a_folder_that_refuses_files_is_exit_2(tmp_path: Path) -> None:
    """``/sys`` as root: ``os.access`` says writable, creating a file fails (EPERM). One line, exit 2."""
    best = save_predictor_checkpoint(tmp_path / "best.pt", PairPredictor(MASt3RBackbone(BackboneConfig.tiny())))
    target = Path("/sys/macsplat-hostile-test.onnx")
    code, _, err = run_cli(["export-onnx", "--checkpoint", best, "-o", target, "--size", "96x64", "-q"])
    assert code == 2 and "cannot write /sys/macsplat-hostile-test.onnx" in one_error_line(err), err
    assert not target.exists()


class _StandIn(torch.nn.Module):
    """A stand-in backbone that exports in seconds: the pixel colours through two matrix products (so the file
    holds ~2 MB of weights)."""

    def __init__(self) -> None:
        super().__init__()
        self.config = BackboneConfig.tiny()
        g = torch.Generator().manual_seed(0)
        self.w1 = torch.nn.Parameter(torch.randn(3, 16384, generator=g) / 16)
        self.w2 = torch.nn.Parameter(torch.randn(16384, 27, generator=g) / 128)

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> tuple[BackboneView, BackboneView]:
        views = []
        for img in (x0, x1):
            _, _, h, w = img.shape
            f = img.permute(0, 2, 3, 1) @ self.w1 @ self.w2  # [B, H, W, 27]
            conf = 1.0 + f[..., 0].exp()
            desc = torch.nn.functional.normalize(f[..., 3:], dim=-1)
            views.append(BackboneView(f[..., :3] + 3.0, conf, desc, conf, (), (h // 16, w // 16)))
        return views[0], views[1]


@pytest.mark.slow  # an export (a stand-in network, still a trace)
def test_export_onto_a_full_disk_is_an_output_error_and_leaves_nothing(tmp_path: Path) -> None:
    predictor = PairPredictor(_StandIn()).eval()  # type: ignore[arg-type]
    out = tmp_path / "out" / "p.onnx"
    with file_size_limit(64 * 1024), pytest.raises(OutputPathError, match="cannot write .*p.onnx: File too large"):
        export_onnx(predictor, out, ExportConfig(size=SIZE, dynamic=False), sample=sample_pair(SIZE))
    assert list(out.parent.iterdir()) == []  # no graph, no parity file, no temporary folder


@pytest.mark.parametrize(
    "sample",
    [
        "size",  # the sample at another size than the export's
        "dtype",  # float64 images
        "one",  # a single view
    ],
)
def test_a_sample_pair_that_does_not_fit_the_export_is_refused_before_any_work(tmp_path: Path, sample: str) -> None:
    predictor = PairPredictor(_StandIn()).eval()  # type: ignore[arg-type]
    good = sample_pair(SIZE)
    bad = {
        "size": sample_pair((SIZE[0] + 16, SIZE[1])),
        "dtype": tuple(t.double() for t in good),
        "one": good[:1],
    }[sample]
    out = tmp_path / "out" / "p.onnx"
    with pytest.raises(InputError, match=r"sample pair must be two float32 \[1, 3, 64, 96\] tensors"):
        export_onnx(predictor, out, ExportConfig(size=SIZE, dynamic=False), sample=bad)  # type: ignore[arg-type]
    assert not out.parent.exists()
    assert [tuple(t.shape) for t in good] == [(1, 3, 64, 96)] * 2 and all(t.dtype == torch.float32 for t in good)
