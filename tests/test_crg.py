"""OpenCRG road surfaces (rough_map.io.crg): ASAM's example files, round trips in the four
data forms written from the specification, the same survey as the grid as a .npy, and
one-line errors on hostile files."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest

from rough_map.errors import FileFormatError, RoughMapError
from rough_map.io.crg import FORMATS, read_crg, write_crg
from rough_map.io.raster import open_height_raster
from rough_map.iso8608 import synthesize_surface
from rough_map.survey import roughness_raster

ASAM = Path(__file__).resolve().parents[2] / "shared" / "data" / "formats" / "opencrg"
B = 0.008


def _asam(name: str) -> Path:
    path = ASAM / name
    if not path.exists():
        pytest.skip(f"{path} is not here")
    return path


def test_the_asam_examples_read_with_their_margins_and_reference_lines() -> None:
    straight = read_crg(_asam("handmade_straight.crg"))
    assert straight.z.shape == (23, 7) and straight.du == 1.0 and straight.dv == 0.5
    np.testing.assert_array_equal(straight.v, [-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5])
    assert np.isnan(straight.z).sum() == 3 and straight.phi is None
    assert straight.z[3, 3] == pytest.approx(0.0111111)
    # the minimalist file is "completely equivalent" to the commented one
    minimal = read_crg(_asam("handmade_straight_minimalist.crg"))
    np.testing.assert_array_equal(minimal.z, straight.z)
    np.testing.assert_array_equal(minimal.v, straight.v)
    double = read_crg(_asam("handmade_straight_double.crg"))
    np.testing.assert_allclose(double.z, straight.z, atol=1e-7)
    full = read_crg(_asam("handmade_curved_banked_sloped.crg"))
    assert full.phi is not None and full.banking is not None and full.slope is not None
    np.testing.assert_array_equal(full.v, [-1.5, -1.25, -1.0, 0.0, 1.0, 1.25, 1.5])
    # the road's heights: long sections plus banking * v plus the integrated slope
    expected = full.z + np.nan_to_num(full.banking)[:, None] * full.v
    slope = np.nan_to_num(full.slope)
    rise = np.concatenate([[0.0], np.cumsum((slope[1:] + slope[:-1]) / 2)])
    np.testing.assert_allclose(full.heights(), expected + rise[:, None])
    with pytest.raises(FileFormatError, match=r"fileref\.crg \[header\]: refers to the CRG"):
        read_crg(_asam("fileref.crg"))


@pytest.mark.parametrize("form", sorted(FORMATS))
def test_a_written_crg_reads_back_in_every_form(form: str, tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    z = rng.normal(0.0, 0.01, size=(41, 9))
    z[:, 0] = np.nan  # a NaN margin
    z[5, 4] = np.nan
    phi = np.linspace(0.0, 0.3, 41)
    path = write_crg(
        tmp_path / "road.crg", z, 0.02, np.linspace(-0.08, 0.08, 9), phi=phi, form=form
    )
    back = read_crg(path)
    assert back.z.shape == z.shape and back.du == pytest.approx(0.02)
    np.testing.assert_allclose(back.v, np.linspace(-0.08, 0.08, 9), atol=1e-12)
    tol = {"KDBI": 0.0, "LDFI": 1e-12, "KRBI": 1e-8, "LRFI": 1e-5}[form]
    np.testing.assert_allclose(back.z, z, rtol=0, atol=tol)
    assert back.phi is not None
    np.testing.assert_allclose(back.phi, phi, atol=max(tol, 1e-7))


def test_a_binary_crg_surveys_as_its_grid_given_as_npy(tmp_path: Path) -> None:
    """The windows of a binary CRG read as the same grid passed as a .npy with its
    spacing: the rows of the raster are the long sections, profiles along u."""
    z = synthesize_surface((900, 240), B, 64e-6, -2.4, seed=3)  # (u, v)
    z[:, :6] = np.nan  # NaN margins
    z[:, -6:] = np.nan
    v = (np.arange(240) - 119.5) * B
    crg = write_crg(tmp_path / "road.crg", z, B, v, form="KRBI")
    grid = np.ascontiguousarray(z[:, ::-1].T.astype(np.float32))  # rows: v from the left
    np.save(tmp_path / "road.npy", grid)
    a = roughness_raster(open_height_raster(crg))
    b = roughness_raster(open_height_raster(tmp_path / "road.npy", spacing=B))
    ok = (a["valid"] > 0) & (b["valid"] > 0)
    assert ok.sum() >= 0.5 * ok.size
    np.testing.assert_array_equal(a["valid"], b["valid"])
    assert np.median(np.abs(np.log(a["R"][ok] / b["R"][ok]))) < 1e-4


def test_hostile_crg_files_get_one_line(tmp_path: Path) -> None:
    z = np.zeros((30, 5))
    v = np.linspace(-0.1, 0.1, 5)
    good = write_crg(tmp_path / "good.crg", z, 0.05, v, form="KRBI").read_bytes()
    (tmp_path / "cut.crg").write_bytes(good[:-7])
    with pytest.raises(FileFormatError, match=r"cut\.crg \[data\]: binary data of \d+ B is not"):
        read_crg(tmp_path / "cut.crg")
    lying = good.replace(
        b"REFERENCE_LINE_END_U     = 1.4500000000000002", b"REFERENCE_LINE_END_U     = 1e12"
    )
    (tmp_path / "lying.crg").write_bytes(lying)
    with pytest.raises(FileFormatError, match=r"lying\.crg \[REFERENCE_LINE_END_U\]: the header"):
        read_crg(tmp_path / "lying.crg")
    six = good.replace(
        b"D:long section at v = 0.1,m\n",
        b"D:long section at v = 0.1,m\nD:long section at v = 0.2,m\n",
    )
    (tmp_path / "six.crg").write_bytes(six)
    with pytest.raises(FileFormatError, match=r"six\.crg \[(data|REFERENCE_LINE_END_U)\]"):
        read_crg(tmp_path / "six.crg")
    bad = z.copy()
    bad[3, 2] = np.inf
    write_crg(tmp_path / "inf.crg", bad, 0.05, v, form="KDBI")
    with pytest.raises(FileFormatError, match=r"inf\.crg \[data\]: an infinite value in record 4"):
        read_crg(tmp_path / "inf.crg")
    (tmp_path / "form.crg").write_bytes(good.replace(b"#:KRBI", b"#:XXXX"))
    with pytest.raises(FileFormatError, match=r"form\.crg \[KD_Definition\]: data form 'XXXX'"):
        read_crg(tmp_path / "form.crg")
    (tmp_path / "none.crg").write_bytes(b"$CT\nnothing\n$\n")
    with pytest.raises(FileFormatError, match=r"none\.crg \[header\]: not an OpenCRG file"):
        read_crg(tmp_path / "none.crg")
    (tmp_path / "empty.crg").write_bytes(b"")
    with pytest.raises(FileFormatError, match=r"empty\.crg"):
        read_crg(tmp_path / "empty.crg")
    text = write_crg(tmp_path / "t.crg", z, 0.05, v, form="LRFI").read_text(encoding="latin-1")
    head, data = text.split("$" * 72 + "\n")
    assert data.startswith(" 0.0000000")
    bad_text = head + "$" * 72 + "\n" + "  garbage!" + data[10:]
    (tmp_path / "nan.crg").write_text(bad_text, "latin-1")
    with pytest.raises(FileFormatError, match=r"nan\.crg \[data\]: record 1: not a number"):
        read_crg(tmp_path / "nan.crg")
    with pytest.raises(FileFormatError, match=r"handmade_straight\.crg \[LONG_SECTION_V_INC"):
        open_height_raster(_asam("handmade_straight.crg"))  # 1 m x 0.5 m cells


@pytest.mark.parametrize("form", sorted(FORMATS))
def test_damaged_crg_files_are_one_line_errors(form: str, tmp_path: Path) -> None:
    """Cut, flipped, inserted and deleted bytes (seeded): the reader and the raster opener
    raise a RoughMapError or read, nothing else."""
    rnd = random.Random(form)
    z = np.random.default_rng(0).normal(0, 0.01, (40, 6))
    base = write_crg(
        tmp_path / "base.crg", z, 0.05, np.linspace(-0.1, 0.15, 6), form=form, phi=np.zeros(40)
    ).read_bytes()
    path = tmp_path / "damaged.crg"
    for _ in range(100):
        data = bytearray(base)
        i = rnd.randrange(len(data))
        op = rnd.randrange(4)
        if op == 0:
            data = data[:i]
        elif op == 1:
            data[i] = rnd.randrange(256)
        elif op == 2:
            data[i:i] = bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 40)))
        else:
            del data[i : i + rnd.randrange(1, 40)]
        path.write_bytes(bytes(data))
        for read in (read_crg, open_height_raster):
            try:
                read(path)
            except RoughMapError:
                pass


@pytest.mark.parametrize("form", ["KRBI", "KDBI"])
def test_whole_nan_records_at_the_end_are_a_margin_not_padding(form: str, tmp_path: Path) -> None:
    """Records all NaN at the end of binary data are the road's margin when the header
    counts them (REFERENCE_LINE_END_U), though they look like the 80-byte NaN padding."""
    z = np.random.default_rng(2).normal(0, 0.01, (31, 3))
    z[:2] = np.nan
    z[-4:] = np.nan
    back = read_crg(write_crg(tmp_path / "m.crg", z, 0.1, [-0.1, 0.0, 0.1], form=form))
    assert back.z.shape == (31, 3)
    np.testing.assert_allclose(back.z, z, rtol=0, atol=1e-8)
