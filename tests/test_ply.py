"""Tests of macsplat_cli.ply: the standard 3DGS PLY layout, foreign files, errors, atomicity."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import plyfile
import pytest
import torch
import trimesh

from macsplat_cli import ply
from macsplat_cli.errors import OutputPathError, PlyFormatError
from macsplat_cli.gaussians import Gaussians
from macsplat_cli.ply import read_ply, write_ply


# ------------------------------------------------------------------------------------ helpers
def random_gaussians(n: int, degree: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Gaussians(
        means=torch.randn(n, 3, generator=g, dtype=dtype) * 3,
        log_scales=torch.randn(n, 3, generator=g, dtype=dtype) - 4,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        opacity_logits=torch.randn(n, generator=g, dtype=dtype),
        sh=torch.randn(n, k, 3, generator=g, dtype=dtype),
    )


def assert_bits_equal(a: Gaussians, b: Gaussians) -> None:
    """Exact float32 bit equality of every parameter (NaN payloads and -0.0 included)."""
    assert a.sh.shape == b.sh.shape
    for name, x, y in zip(("means", "log_scales", "quats", "opacity_logits", "sh"), a.tensors(), b.tensors()):
        assert x.dtype == y.dtype == torch.float32, name
        assert torch.equal(x.contiguous().view(torch.int32), y.contiguous().view(torch.int32)), name


def standard_names(degree: int, normals: bool = True) -> list[str]:
    """The standard property order, spelled out independently of the module under test."""
    n_rest = 3 * ((degree + 1) ** 2 - 1)
    return (
        ["x", "y", "z"]
        + (["nx", "ny", "nz"] if normals else [])
        + ["f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def columns_of(g: Gaussians) -> dict[str, np.ndarray]:
    """Expected per-property values of ``g`` (float64 copies), computed the slow obvious way."""
    n, k = g.sh.shape[0], g.sh.shape[1]
    cols: dict[str, np.ndarray] = {}
    for i, axis in enumerate("xyz"):
        cols[axis] = g.means[:, i].double().numpy()
    for c in range(3):
        cols[f"f_dc_{c}"] = g.sh[:, 0, c].double().numpy()
        for j in range(1, k):
            cols[f"f_rest_{c * (k - 1) + (j - 1)}"] = g.sh[:, j, c].double().numpy()
    cols["opacity"] = g.opacity_logits.double().numpy()
    for i in range(3):
        cols[f"scale_{i}"] = g.log_scales[:, i].double().numpy()
    for i in range(4):
        cols[f"rot_{i}"] = g.quats[:, i].double().numpy()
    assert all(v.shape == (n,) for v in cols.values())
    return cols


def write_with_plyfile(path: Path, fields: list[tuple[str, str, np.ndarray]], **kwargs: object) -> None:
    """Write one ``vertex`` element with the given (name, dtype, values) fields using plyfile."""
    n = len(fields[0][2])
    arr = np.empty(n, dtype=[(name, dt) for name, dt, _ in fields])
    for name, _, values in fields:
        arr[name] = values
    elements = [plyfile.PlyElement.describe(arr, "vertex")]
    extra = kwargs.pop("extra_elements", [])
    plyfile.PlyData(elements + list(extra), **kwargs).write(str(path))  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------ round trip
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("normals", [True, False])
def test_round_trip_is_bit_exact(tmp_path: Path, degree: int, normals: bool) -> None:
    g = random_gaussians(257, degree, seed=degree)
    # Awkward values must survive too: negative zero, subnormals, extremes.
    g.means[0] = torch.tensor([-0.0, 1e-45, 3.4e38])
    g.opacity_logits[1] = -1e-40
    path = tmp_path / "scene.ply"
    assert write_ply(path, g, normals=normals) == 257
    back = read_ply(path)
    assert back.sh_degree == degree
    assert back.device == torch.device("cpu")
    assert_bits_equal(g, back)


def test_fast_path_and_plyfile_path_agree(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "scene.ply"
    g = random_gaussians(100, 3, seed=4)
    write_ply(path, g)
    fast = read_ply(path)
    calls: list[Path] = []
    real = ply._read_plyfile

    def spy(p: Path) -> ply._StructuredColumns:
        calls.append(p)
        return real(p)

    monkeypatch.setattr(ply, "_read_fast", lambda *args: None)
    monkeypatch.setattr(ply, "_read_plyfile", spy)
    slow = read_ply(path)
    assert calls == [path]
    assert_bits_equal(fast, slow)
    assert_bits_equal(g, slow)


def test_empty_set_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "empty.ply"
    assert write_ply(path, Gaussians.empty(sh_degree=2)) == 0
    back = read_ply(path)
    assert len(back) == 0 and back.sh_degree == 2


def test_float64_and_requires_grad_are_accepted(tmp_path: Path) -> None:
    g64 = random_gaussians(50, 1, seed=7, dtype=torch.float64)
    g64 = Gaussians(*(t.clone().requires_grad_(True) for t in g64.tensors()))
    path = tmp_path / "scene.ply"
    assert write_ply(path, g64) == 50
    assert_bits_equal(g64.detach().to(torch.float32), read_ply(path))


# ------------------------------------------------------------------------------------ layout
def test_header_bytes_are_exactly_standard(tmp_path: Path) -> None:
    path = tmp_path / "scene.ply"
    write_ply(path, random_gaussians(3, 1))
    data = path.read_bytes()
    expected = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
        b"property float x\nproperty float y\nproperty float z\n"
        b"property float nx\nproperty float ny\nproperty float nz\n"
        b"property float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n"
        + b"".join(b"property float f_rest_%d\n" % i for i in range(9))
        + b"property float opacity\n"
        b"property float scale_0\nproperty float scale_1\nproperty float scale_2\n"
        b"property float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\n"
        b"end_header\n"
    )
    assert data.startswith(expected)
    assert len(data) == len(expected) + 3 * 26 * 4  # 26 float32 properties at degree 1
    assert b"\r" not in data[: len(expected)]


@pytest.mark.parametrize("normals", [True, False])
def test_plyfile_sees_standard_layout_and_values(tmp_path: Path, normals: bool) -> None:
    g = random_gaussians(40, 3, seed=1)
    path = tmp_path / "scene.ply"
    write_ply(path, g, normals=normals)
    data = plyfile.PlyData.read(str(path))
    assert not data.text and data.byte_order == "<"
    assert [el.name for el in data.elements] == ["vertex"]
    vertex = data["vertex"]
    assert [p.name for p in vertex.properties] == standard_names(3, normals)
    assert len(vertex.properties) == (62 if normals else 59)
    assert all(p.val_dtype == "f4" for p in vertex.properties)
    assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in vertex.data.dtype.names)
    # Channel-major f_rest, raw pre-activation values, zero normals.
    for name, values in columns_of(g).items():
        np.testing.assert_array_equal(vertex[name].astype(np.float64), values, err_msg=name)
    np.testing.assert_array_equal(vertex["f_rest_0"], g.sh[:, 1, 0].numpy())  # R, band 1
    np.testing.assert_array_equal(vertex["f_rest_15"], g.sh[:, 1, 1].numpy())  # G, band 1
    np.testing.assert_array_equal(vertex["f_rest_44"], g.sh[:, 15, 2].numpy())  # B, last coefficient
    if normals:
        for name in ("nx", "ny", "nz"):
            assert not vertex[name].any()


def test_trimesh_loads_positions(tmp_path: Path) -> None:
    g = random_gaussians(64, 3, seed=2)
    path = tmp_path / "scene.ply"
    write_ply(path, g)
    loaded = trimesh.load(path)
    vertices = np.asarray(loaded.vertices)
    assert vertices.shape == (64, 3)
    np.testing.assert_array_equal(vertices, g.means.numpy().astype(np.float64))


# ------------------------------------------------------------------------------------ foreign files
def test_foreign_order_types_and_extras(tmp_path: Path) -> None:
    g = random_gaussians(30, 2, seed=3)
    cols = columns_of(g)
    names = list(cols)
    rng = np.random.default_rng(0)
    rng.shuffle(names)
    # Doubles for some properties, floats for others, an extra uchar property, no normals.
    fields = [(name, "<f8" if i % 2 else "<f4", cols[name]) for i, name in enumerate(names)]
    fields.insert(5, ("red", "u1", np.arange(30) % 256))
    faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "O")])
    extra = plyfile.PlyElement.describe(faces, "face")
    path = tmp_path / "foreign.ply"
    write_with_plyfile(path, fields, extra_elements=[extra])
    back = read_ply(path)
    assert back.sh_degree == 2
    assert_bits_equal(g, back)  # float32 values stored as doubles round-trip exactly


def test_doubles_are_rounded_to_float32(tmp_path: Path) -> None:
    g = random_gaussians(20, 0, seed=5)
    cols = {name: values + 1e-12 for name, values in columns_of(g).items()}  # not float32-representable
    path = tmp_path / "double.ply"
    write_with_plyfile(path, [(name, "<f8", values) for name, values in cols.items()])
    back = read_ply(path)
    np.testing.assert_array_equal(back.means[:, 0].numpy(), cols["x"].astype(np.float32))
    np.testing.assert_array_equal(back.quats[:, 3].numpy(), cols["rot_3"].astype(np.float32))


@pytest.mark.parametrize("variant", ["ascii", "big_endian"])
def test_ascii_and_big_endian_read_identically(tmp_path: Path, variant: str) -> None:
    g = random_gaussians(25, 3, seed=6)
    standard = tmp_path / "standard.ply"
    write_ply(standard, g)
    data = plyfile.PlyData.read(str(standard))
    other = tmp_path / f"{variant}.ply"
    if variant == "ascii":
        plyfile.PlyData(data.elements, text=True).write(str(other))
        assert other.read_bytes().startswith(b"ply\nformat ascii 1.0\n")
    else:
        plyfile.PlyData(data.elements, byte_order=">").write(str(other))
        assert other.read_bytes().startswith(b"ply\nformat binary_big_endian 1.0\n")
    assert_bits_equal(read_ply(standard), read_ply(other))


def test_degree_4_is_truncated_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    n, k4 = 12, 25
    rng = np.random.default_rng(1)
    sh4 = rng.standard_normal((n, k4, 3)).astype(np.float32)
    g = random_gaussians(n, 0, seed=8)
    cols = columns_of(g)
    for c in range(3):
        cols[f"f_dc_{c}"] = sh4[:, 0, c].astype(np.float64)
        for j in range(1, k4):
            cols[f"f_rest_{c * (k4 - 1) + j - 1}"] = sh4[:, j, c].astype(np.float64)
    assert sum(name.startswith("f_rest_") for name in cols) == 72
    path = tmp_path / "deg4.ply"
    write_with_plyfile(path, [(name, "<f4", values) for name, values in cols.items()])
    with caplog.at_level(logging.WARNING, logger="macsplat_cli.ply"):
        back = read_ply(path)
    assert back.sh_degree == 3
    np.testing.assert_array_equal(back.sh.numpy(), sh4[:, :16, :])
    assert any("truncated" in r.getMessage() and "4" in r.getMessage() for r in caplog.records)


def test_sh_count_not_matching_a_degree_is_an_error(tmp_path: Path) -> None:
    cols = columns_of(random_gaussians(5, 0))
    for i in range(10):
        cols[f"f_rest_{i}"] = np.zeros(5)
    path = tmp_path / "odd.ply"
    write_with_plyfile(path, [(name, "<f4", values) for name, values in cols.items()])
    with pytest.raises(PlyFormatError, match="10 f_rest"):
        read_ply(path)


def test_missing_property_is_named(tmp_path: Path) -> None:
    cols = columns_of(random_gaussians(5, 1))
    del cols["opacity"]
    del cols["rot_2"]
    path = tmp_path / "no_opacity.ply"
    write_with_plyfile(path, [(name, "<f4", values) for name, values in cols.items()])
    with pytest.raises(PlyFormatError) as info:
        read_ply(path)
    message = str(info.value)
    assert "opacity" in message and "rot_2" in message and str(path) in message
    assert "rot_1" not in message


def test_file_without_vertex_element(tmp_path: Path) -> None:
    arr = np.zeros(3, dtype=[("x", "<f4")])
    path = tmp_path / "points.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "point")]).write(str(path))
    with pytest.raises(PlyFormatError, match="vertex"):
        read_ply(path)


# ------------------------------------------------------------------------------------ bad files
def _assert_one_line_naming(err: pytest.ExceptionInfo[PlyFormatError], path: Path) -> None:
    message = str(err.value)
    assert str(path) in message
    assert "\n" not in message


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.ply"
    with pytest.raises(PlyFormatError, match="no such file") as err:
        read_ply(path)
    _assert_one_line_naming(err, path)


def test_directory_is_not_a_ply(tmp_path: Path) -> None:
    with pytest.raises(PlyFormatError, match="directory"):
        read_ply(tmp_path)


@pytest.mark.parametrize("content", [b"", b"hello world\n", b"\x89PNG\r\n\x1a\n" + bytes(100)])
def test_not_a_ply(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(PlyFormatError, match="not a PLY") as err:
        read_ply(path)
    _assert_one_line_naming(err, path)


def test_broken_header(tmp_path: Path) -> None:
    path = tmp_path / "bad.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty floot x\nend_header\n")
    with pytest.raises(PlyFormatError) as err:
        read_ply(path)
    _assert_one_line_naming(err, path)


@pytest.mark.parametrize("cut", [1, 100, 248 * 5])
def test_truncated_file(tmp_path: Path, cut: int) -> None:
    path = tmp_path / "scene.ply"
    write_ply(path, random_gaussians(10, 3))
    data = path.read_bytes()
    path.write_bytes(data[:-cut])
    with pytest.raises(PlyFormatError) as err:
        read_ply(path)
    _assert_one_line_naming(err, path)


def test_truncated_header(tmp_path: Path) -> None:
    path = tmp_path / "scene.ply"
    write_ply(path, random_gaussians(10, 0))
    path.write_bytes(path.read_bytes()[:60])
    with pytest.raises(PlyFormatError) as err:
        read_ply(path)
    _assert_one_line_naming(err, path)


# ------------------------------------------------------------------------------------ non-finite
def test_non_finite_rows_are_dropped_on_write(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    g = random_gaussians(10, 1, seed=9)
    g.sh[2, 3, 1] = float("nan")
    g.means[5, 0] = float("inf")
    g.opacity_logits[7] = float("-inf")
    path = tmp_path / "scene.ply"
    with caplog.at_level(logging.WARNING, logger="macsplat_cli.ply"):
        assert write_ply(path, g) == 7
    assert any("dropped 3 of 10" in r.getMessage() for r in caplog.records)
    keep = torch.tensor([i not in (2, 5, 7) for i in range(10)])
    assert_bits_equal(g[keep], read_ply(path))
    assert plyfile.PlyData.read(str(path))["vertex"].count == 7


def test_non_finite_rows_are_dropped_on_read(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    g = random_gaussians(8, 0, seed=10)
    cols = columns_of(g)
    cols["scale_1"][3] = np.nan
    cols["rot_0"][6] = np.inf
    path = tmp_path / "nan.ply"
    write_with_plyfile(path, [(name, "<f4", values) for name, values in cols.items()])
    with caplog.at_level(logging.WARNING, logger="macsplat_cli.ply"):
        back = read_ply(path)
    assert len(back) == 6
    assert any("dropped 2 of 8" in r.getMessage() for r in caplog.records)
    keep = torch.tensor([i not in (3, 6) for i in range(8)])
    assert_bits_equal(g[keep], back)


def test_non_finite_in_ignored_property_is_kept(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    g = random_gaussians(4, 0, seed=11)
    fields = [(name, "<f4", values) for name, values in columns_of(g).items()]
    fields.append(("nx", "<f4", np.array([np.nan, 0, 0, 0])))
    path = tmp_path / "nan_normal.ply"
    write_with_plyfile(path, fields)
    with caplog.at_level(logging.WARNING, logger="macsplat_cli.ply"):
        assert len(read_ply(path)) == 4
    assert not caplog.records


# ------------------------------------------------------------------------------------ output paths
def test_missing_folders_are_created(tmp_path: Path) -> None:
    assert write_ply(tmp_path / "new" / "dir" / "scene.ply", random_gaussians(3, 0)) == 3
    assert [p.name for p in (tmp_path / "new" / "dir").iterdir()] == ["scene.ply"]


def test_path_under_a_file_is_an_output_error(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputPathError, match="is a file"):
        write_ply(tmp_path / "file" / "scene.ply", random_gaussians(3, 0))
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


def test_failed_write_leaves_nothing_behind(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[str] = []

    def failing_write(f, header, records):  # noqa: ANN001, ANN202 - test double
        seen.append(f.name)
        assert Path(f.name).exists()  # the temporary file exists while writing
        f.write(header)
        f.write(records.data[: records.nbytes // 2])
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(ply, "_write_records", failing_write)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_ply(tmp_path / "scene.ply", random_gaussians(100, 3))
    assert len(seen) == 1 and Path(seen[0]).parent == tmp_path
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "scene.ply"
    write_ply(path, random_gaussians(5, 0, seed=1))
    before = path.read_bytes()

    def failing_write(f, header, records):  # noqa: ANN001, ANN202 - test double
        f.write(header)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ply, "_write_records", failing_write)
    with pytest.raises(OutputPathError, match="No space left"):
        write_ply(path, random_gaussians(5, 0, seed=2))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["scene.ply"]


def test_written_file_has_normal_permissions(tmp_path: Path) -> None:
    path = tmp_path / "scene.ply"
    write_ply(path, random_gaussians(2, 0))
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_end_header_inside_a_comment_does_not_end_the_header(tmp_path: Path, fmt: str) -> None:
    """Issue 37 P1: a ``comment end_header`` line before the element line is a comment; the element's claimed
    count (2³¹ rows) is checked against the body's size before anything is allocated."""
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2"]
    names += ["rot_0", "rot_1", "rot_2", "rot_3"]
    header = f"ply\nformat {fmt} 1.0\ncomment end_header\nelement vertex {2**31}\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    path = tmp_path / "bomb.ply"
    path.write_bytes(header.encode() + b"0 " * 17 + b"\n")
    with pytest.raises(PlyFormatError, match=r"declares 2147483648 'vertex' elements") as err:
        read_ply(path)
    _assert_one_line_naming(err, path)


def test_comment_mentioning_end_header_is_read_as_a_comment(tmp_path: Path) -> None:
    """A file whose comment says ``end_header`` reads like the same file without the comment (fast path and
    plyfile)."""
    path = tmp_path / "scene.ply"
    g = random_gaussians(5, 1)
    write_ply(path, g)
    data = path.read_bytes()
    commented = tmp_path / "commented.ply"
    commented.write_bytes(data.replace(b"\nelement", b"\ncomment end_header here\nelement", 1))
    assert_bits_equal(read_ply(commented), read_ply(path))
