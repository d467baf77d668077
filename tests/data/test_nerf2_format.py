"""The NeRF2 folder reader: the real s23 slice, format variants, and a clear error for each bad input."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from PIL import Image

from graf.data.nerf2_format import DataFormatError, read_nerf2_folder, seeded_split, write_nerf2_folder
from tests.conftest import EMBEDDED_S23, smooth_spectra


def test_reads_real_s23_slice():
    d = read_nerf2_folder(EMBEDDED_S23)
    assert tuple(d.spectra.shape) == (200, 90, 360)
    assert (d.n_train, d.n_test) == (160, 40)
    assert float(d.spectra.min()) == 0.0 and float(d.spectra.max()) == 1.0  # min-max scaled per spectrum
    assert d.meta["tx_pos_header"] is True
    np.testing.assert_allclose(d.gateway_position, [5.0, 0.26, 0.0])
    # id 132 is the first training id; its position is data row 132 of tx_pos.csv
    rows = (EMBEDDED_S23 / "tx_pos.csv").read_text().splitlines()
    assert d.ids[0] == 132
    np.testing.assert_allclose(d.positions[0], [float(v) for v in rows[132].split(",")])
    # pixel / 255 label convention
    png = np.asarray(Image.open(EMBEDDED_S23 / "spectrum" / "00132.png"), dtype=np.float32) / 255
    np.testing.assert_array_equal(d.spectra[0].numpy(), png)
    assert set(d.ids[d.train_idx]).isdisjoint(d.ids[d.test_idx])


def _copy(tmp_path):
    dst = tmp_path / "s23"
    shutil.copytree(EMBEDDED_S23, dst)
    return dst


def test_unpadded_ids_and_headerless_positions(tmp_path):
    root = _copy(tmp_path)
    for f in (root / "spectrum").iterdir():
        f.rename(f.with_name(f"{int(f.stem)}.png"))
    lines = (root / "tx_pos.csv").read_text().splitlines()[1:]
    (root / "tx_pos.csv").write_text("\n".join(lines) + "\n")
    for idx in ("train_index.txt", "test_index.txt"):
        (root / idx).write_text("\n".join(str(int(x)) for x in (root / idx).read_text().split()) + "\n")
    a, b = read_nerf2_folder(EMBEDDED_S23), read_nerf2_folder(root)
    assert b.meta["tx_pos_header"] is False
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_allclose(a.positions, b.positions)
    assert bool((a.spectra == b.spectra).all())


def test_missing_index_files_give_seeded_documented_split(tmp_path):
    root = _copy(tmp_path)
    (root / "train_index.txt").unlink()
    (root / "test_index.txt").unlink()
    a = read_nerf2_folder(root, split_seed=7)
    b = read_nerf2_folder(root, split_seed=7)
    c = read_nerf2_folder(root, split_seed=8)
    assert (a.n_train, a.n_test) == (160, 40)
    assert "seed=7" in a.split_source
    np.testing.assert_array_equal(a.ids, b.ids)
    assert not np.array_equal(a.ids, c.ids)
    assert seeded_split(list(range(1, 11)), 0, 0.8) == seeded_split(list(range(10, 0, -1)), 0, 0.8)


def test_write_read_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(6, 3))
    spectra = smooth_spectra(pos)
    ids = np.array([3, 1, 2, 6, 5, 4])
    root = write_nerf2_folder(
        tmp_path / "rt", spectra, pos, ids, np.zeros(3), np.array([0, 0, 0, 1.0]), train_ids=ids[:4], test_ids=ids[4:]
    )
    d = read_nerf2_folder(root)
    np.testing.assert_array_equal(d.ids, ids)
    np.testing.assert_allclose(d.positions, pos, atol=1e-6)
    assert np.abs(d.spectra.numpy() - spectra).max() <= 0.5 / 255 + 1e-6  # 8-bit quantisation


# ---------------------------------------------------------------- bad input: one test per problem
def _expect(root, match, file_name=None, **kw):
    with pytest.raises(DataFormatError, match=match) as info:
        read_nerf2_folder(root, **kw)
    if file_name:
        assert file_name in str(info.value)
    return info.value


def test_error_listed_id_without_spectrum(tmp_path):
    root = _copy(tmp_path)
    (root / "spectrum" / "00132.png").unlink()
    _expect(root, "lists id 132 but spectrum/ has no PNG", "train_index.txt")


def test_error_spectrum_wrong_size(tmp_path):
    root = _copy(tmp_path)
    Image.new("L", (360, 89)).save(root / "spectrum" / "00182.png")
    _expect(root, r"89x360 .*expected 90x360", "00182.png")


def test_error_spectrum_not_grayscale(tmp_path):
    root = _copy(tmp_path)
    Image.new("RGB", (360, 90)).save(root / "spectrum" / "00023.png")
    _expect(root, "not 8-bit grayscale.*'RGB'", "00023.png")


def test_error_spectrum_not_a_png(tmp_path):
    root = _copy(tmp_path)
    (root / "spectrum" / "00023.png").write_bytes(b"not a png")
    _expect(root, "cannot be read as a PNG", "00023.png")


def test_error_position_row_missing(tmp_path):
    root = _copy(tmp_path)
    lines = (root / "tx_pos.csv").read_text().splitlines()
    (root / "tx_pos.csv").write_text("\n".join(lines[:150]) + "\n")  # header + 149 rows
    _expect(root, r"has 149 position rows but spectrum id \d+ needs row \d+", "tx_pos.csv")


def test_error_position_not_finite(tmp_path):
    root = _copy(tmp_path)
    lines = (root / "tx_pos.csv").read_text().splitlines()
    lines[132] = "nan,0.1,1.0"
    (root / "tx_pos.csv").write_text("\n".join(lines) + "\n")
    _expect(root, "position of spectrum id 132 .* not finite", "tx_pos.csv")


def test_error_position_not_numeric(tmp_path):
    root = _copy(tmp_path)
    lines = (root / "tx_pos.csv").read_text().splitlines()
    lines[5] = "0.1,abc,1.0"
    (root / "tx_pos.csv").write_text("\n".join(lines) + "\n")
    _expect(root, "line 6 is not numeric", "tx_pos.csv")


def test_error_duplicate_spectrum_ids(tmp_path):
    root = _copy(tmp_path)
    shutil.copy(root / "spectrum" / "00023.png", root / "spectrum" / "23.png")
    _expect(root, "duplicate spectrum id 23", "spectrum")


def test_error_duplicate_ids_in_index(tmp_path):
    root = _copy(tmp_path)
    with open(root / "test_index.txt", "a") as f:
        f.write("\n" + (root / "test_index.txt").read_text().split()[0] + "\n")
    _expect(root, "duplicate id", "test_index.txt")


def test_error_id_in_both_splits(tmp_path):
    root = _copy(tmp_path)
    with open(root / "test_index.txt", "a") as f:
        f.write("\n00132\n")
    _expect(root, r"ids also in train_index.txt: \[132\]", "test_index.txt")


@pytest.mark.parametrize("key", ["position", "orientation"])
def test_error_gateway_without_key(tmp_path, key):
    root = _copy(tmp_path)
    other = "orientation" if key == "position" else "position"
    value = "[0.5, -0.5, -0.5, 0.5]" if other == "orientation" else "[5.0, 0.26, 0]"
    (root / "gateway_info.yml").write_text(f"gateway1:\n  {other}: {value}\n")
    _expect(root, f"gateway1 has no {key}", "gateway_info.yml")


def test_error_gateway_bad_quaternion(tmp_path):
    root = _copy(tmp_path)
    (root / "gateway_info.yml").write_text("gateway1:\n  position: [5, 0, 0]\n  orientation: [1, 1, 0]\n")
    _expect(root, "orientation must be 4 finite numbers", "gateway_info.yml")


def test_error_one_index_file_missing(tmp_path):
    root = _copy(tmp_path)
    (root / "test_index.txt").unlink()
    _expect(root, "missing while train_index.txt exists", "test_index.txt")


def test_error_non_integer_id(tmp_path):
    root = _copy(tmp_path)
    (root / "spectrum" / "00023.png").rename(root / "spectrum" / "abc.png")
    _expect(root, "'abc' is not an integer", "abc.png")


def test_error_missing_folder(tmp_path):
    _expect(tmp_path / "nope", "scene folder does not exist", "nope")


# ---------------------------------------------------------------- the reader does not guess silently
def _small_positions(n):
    return (np.arange(3 * n, dtype=np.float64).reshape(n, 3) + 0.5) / 10


def _small_folder(tmp_path, n=5, header=True, spectra=None, index=True):
    """A written folder with ids 1..n at distinct positions; ``header=False`` drops tx_pos.csv's header."""
    pos = _small_positions(n)
    ids = np.arange(1, n + 1)
    if spectra is None:
        spectra = smooth_spectra(pos)
    kw = {"train_ids": ids[: n - 1], "test_ids": ids[n - 1 :]} if index else {}
    root = write_nerf2_folder(tmp_path / "small", spectra, pos, ids, np.zeros(3), np.array([0, 0, 0, 1.0]), **kw)
    if not header:
        csv_path = root / "tx_pos.csv"
        csv_path.write_text("\n".join(csv_path.read_text().splitlines()[1:]) + "\n")
    return root, pos


def test_error_headerless_positions_with_partly_numeric_first_row(tmp_path):
    root, _ = _small_folder(tmp_path, header=False)
    lines = (root / "tx_pos.csv").read_text().splitlines()
    lines[0] = "1.0,2.0,abc"
    (root / "tx_pos.csv").write_text("\n".join(lines) + "\n")
    err = _expect(root, r"line 1 .* neither a header .* nor a numeric x,y,z row", "tx_pos.csv")
    assert "'abc'" in err.problem


def test_error_headerless_positions_with_garbage_first_row_is_not_shifted(tmp_path):
    # a first row with no numeric cell that does not name x, y, z is neither a header nor a position:
    # refused at line 1, instead of every spectrum taking the next row's position
    root, _ = _small_folder(tmp_path, header=False)
    lines = (root / "tx_pos.csv").read_text().splitlines()
    lines[0] = "abc,def,ghi"
    (root / "tx_pos.csv").write_text("\n".join(lines) + "\n")
    err = _expect(root, r"line 1 'abc,def,ghi' looks like a header \(no numeric cell\) but is not one", "tx_pos.csv")
    assert "unknown names 'abc', 'def', 'ghi'" in err.problem


def test_error_header_row_with_wrong_cell_count(tmp_path):
    root, _ = _small_folder(tmp_path)
    lines = (root / "tx_pos.csv").read_text().splitlines()
    lines[0] = "x,y"
    (root / "tx_pos.csv").write_text("\n".join(lines) + "\n")
    _expect(root, r"line 1 .* looks like a header .* has 2 cells; expected 3", "tx_pos.csv")


def test_bom_before_header_reads_same_positions(tmp_path):
    root, pos = _small_folder(tmp_path)
    plain = read_nerf2_folder(root)
    csv_path = root / "tx_pos.csv"
    csv_path.write_bytes(b"\xef\xbb\xbf" + csv_path.read_bytes())
    d = read_nerf2_folder(root)
    assert d.meta["tx_pos_header"] is True
    np.testing.assert_array_equal(d.ids, plain.ids)
    np.testing.assert_array_equal(d.positions, plain.positions)
    np.testing.assert_allclose(d.positions, pos[d.ids - 1], atol=1e-6)


def test_bom_before_headerless_numeric_row_is_id_1(tmp_path):
    root, pos = _small_folder(tmp_path, header=False)
    csv_path = root / "tx_pos.csv"
    csv_path.write_bytes(b"\xef\xbb\xbf" + csv_path.read_bytes())
    d = read_nerf2_folder(root)
    assert d.meta["tx_pos_header"] is False
    np.testing.assert_array_equal(d.ids, [1, 2, 3, 4, 5])
    np.testing.assert_allclose(d.positions, pos, rtol=0, atol=1e-9)  # row 1 is id 1, no shift


def test_error_jpeg_named_png(tmp_path):
    root, _ = _small_folder(tmp_path)
    Image.new("L", (360, 90), 128).save(root / "spectrum" / "00003.png", format="JPEG")
    _expect(root, r"cannot be read as a PNG image: it is a JPEG file", "00003.png")


def test_warns_constant_spectrum(tmp_path):
    spectra = smooth_spectra(_small_positions(5))
    spectra[2] = 0.5
    root, _ = _small_folder(tmp_path, spectra=spectra)
    with pytest.warns(UserWarning, match=r"small: spectrum id 3 is constant \(all 0\.502\)"):
        d = read_nerf2_folder(root)
    assert d.spectra.shape[0] == 5  # read, not refused


def test_warns_all_zero_spectra(tmp_path):
    spectra = smooth_spectra(_small_positions(5))
    spectra[1] = 0.0
    spectra[4] = 0.0
    root, _ = _small_folder(tmp_path, spectra=spectra)
    with pytest.warns(UserWarning, match=r"small: spectrum ids \[2, 5\] are constant \(all 0\.000\)"):
        read_nerf2_folder(root)


def test_error_one_spectrum_without_index_files(tmp_path):
    root, _ = _small_folder(tmp_path, n=1, index=False)
    _expect(
        root,
        r"1 spectrum and no index files: a seeded split needs at least 2 \(one to train on, one to test\)",
        "small",
    )


# ---------------------------------------------------------------- positions never shift against spectrum ids
# tx_pos.csv data row k is spectrum id k, and NeRF2 writes one row per spectrum: the number of data rows must
# equal the largest spectrum id in spectrum/ (``position_rows="at_least"`` accepts more, with a warning).
def _csv_lines(root):
    return (root / "tx_pos.csv").read_text().splitlines()


def _write_csv_lines(root, lines):
    (root / "tx_pos.csv").write_text("\n".join(lines) + "\n")


def test_real_s23_slice_has_one_row_per_id():
    d = read_nerf2_folder(EMBEDDED_S23)
    assert b"\r\n" in (EMBEDDED_S23 / "tx_pos.csv").read_bytes()  # CRLF, as shipped
    assert d.meta["position_rows"] == {"rows": 200, "largest_id": 200, "rule": "exact"}


def test_error_duplicated_position_row(tmp_path):
    root, _ = _small_folder(tmp_path)  # header + rows for ids 1..5
    lines = _csv_lines(root)
    _write_csv_lines(root, lines[:3] + [lines[2]] + lines[3:])  # id 2's row twice: ids 3..5 would shift
    err = _expect(root, r"has 6 position rows but the largest spectrum id in spectrum/ is 5", "tx_pos.csv")
    assert "shift every later id's position" in err.problem


def test_error_headerless_na_first_row_with_extra_rows(tmp_path):
    # NA,NA,NA is id 1's (unknown) position, not a header; taken as one, every id read the next row
    root, _ = _small_folder(tmp_path, header=False)
    lines = _csv_lines(root)
    lines[0] = "NA,NA,NA"
    _write_csv_lines(root, lines + ["9.5,9.5,9.5"])
    err = _expect(root, r"line 1 'NA,NA,NA' looks like a header \(no numeric cell\) but is not one", "tx_pos.csv")
    assert "found names ['NA', 'NA', 'NA']" in err.problem and "expected x, y, z" in err.problem


def test_error_row_of_empty_cells_is_refused_not_skipped(tmp_path):
    root, _ = _small_folder(tmp_path)
    lines = _csv_lines(root)
    lines[3] = ",,"  # id 3's row is empty: skipping it would move ids 4, 5 onto the rows of 5 and the extra one
    _write_csv_lines(root, lines + ["9.5,9.5,9.5"])
    _expect(root, r"line 4 is not numeric: ',,'", "tx_pos.csv")


def test_error_more_rows_than_largest_id(tmp_path):
    root, _ = _small_folder(tmp_path)
    _write_csv_lines(root, _csv_lines(root) + ["9.5,9.5,9.5"])
    err = _expect(root, r"has 6 position rows but the largest spectrum id in spectrum/ is 5", "tx_pos.csv")
    assert "position_rows='at_least'" in err.problem  # says how to read a slice of a larger dataset


def test_more_rows_than_largest_id_accepted_with_warning_when_at_least(tmp_path, caplog):
    root, pos = _small_folder(tmp_path)
    _write_csv_lines(root, _csv_lines(root) + ["9.5,9.5,9.5", "8.5,8.5,8.5"])
    with caplog.at_level("WARNING", logger="graf.data.nerf2_format"):
        d = read_nerf2_folder(root, position_rows="at_least")
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "tx_pos.csv" in r.getMessage()]
    assert len(warned) == 1
    assert "7 position rows" in warned[0] and "largest spectrum id in spectrum/ is 5" in warned[0]
    assert "2 rows" in warned[0]
    np.testing.assert_array_equal(d.positions, pos[d.ids - 1])
    assert d.meta["position_rows"] == {"rows": 7, "largest_id": 5, "rule": "at_least"}


@pytest.mark.parametrize("rule", ["exact", "at_least"])
def test_error_fewer_rows_than_largest_png_id(tmp_path, rule):
    # the index files list ids 1..4 only (rows exist for them) but spectrum/ holds 00005.png: a row is missing
    root, _ = _small_folder(tmp_path)
    (root / "train_index.txt").write_text("1\n2\n3\n")
    (root / "test_index.txt").write_text("4\n")
    _write_csv_lines(root, _csv_lines(root)[:-1])
    kw = {} if rule == "exact" else {"position_rows": rule}  # exact is the default
    err = _expect(
        root, r"has 4 position rows but the largest spectrum id in spectrum/ is 5 \(00005\.png\)", "tx_pos.csv", **kw
    )
    assert "shift every later id's position" in err.problem


def test_header_columns_read_by_name(tmp_path):
    root, pos = _small_folder(tmp_path)
    lines = _csv_lines(root)
    _write_csv_lines(root, ["z,y,x"] + [",".join(line.split(",")[::-1]) for line in lines[1:]])
    d = read_nerf2_folder(root)
    assert d.meta["tx_pos_header"] is True
    np.testing.assert_array_equal(d.positions, pos[d.ids - 1])  # x and z not swapped


@pytest.mark.parametrize("header, order", [("X, Y ,Z", "xyz"), (" Z ,y, X", "zyx"), ("y,Z,x", "yzx")])
def test_header_names_any_case_spaces_and_order(tmp_path, header, order):
    root, pos = _small_folder(tmp_path)
    rows = [",".join(repr(float(p["xyz".index(c)])) for c in order) for p in pos]
    _write_csv_lines(root, [header] + rows)
    d = read_nerf2_folder(root)
    np.testing.assert_array_equal(d.positions, pos[d.ids - 1])


@pytest.mark.parametrize(
    "header, problem",
    [
        ("x,y,w", "unknown name 'w'"),
        ("x,x,y", "repeated 'x'"),
        ("a,b,c", "unknown names 'a', 'b', 'c'"),
    ],
)
def test_error_header_with_other_names(tmp_path, header, problem):
    root, _ = _small_folder(tmp_path)
    _write_csv_lines(root, [header] + _csv_lines(root)[1:])
    err = _expect(root, rf"line 1 '{header}' looks like a header \(no numeric cell\) but is not one", "tx_pos.csv")
    assert problem in err.problem and f"found names {header.split(',')!r}" in err.problem


def test_error_unknown_position_rows_rule(tmp_path):
    root, _ = _small_folder(tmp_path)
    with pytest.raises(ValueError, match=r"position_rows.*'exact' or 'at_least'.*'sometimes'"):
        read_nerf2_folder(root, position_rows="sometimes")
