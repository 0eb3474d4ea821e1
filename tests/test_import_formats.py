"""`dlo import` reads plain arrays (.npy/.npz/.h5) and motion-capture CSV as it reads
DEFORM's pickles: the same recording gives the same dataset; a bad file is one line."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from dlocli.data import MarkerDataset, load_dataset

from tiny import MARKERS, dlo_import, swinging_cable

SPLITS = {"train": 3, "eval": 2}


def _recordings() -> dict[str, list[np.ndarray]]:
    """(frames, 3, V) arrays, as tiny.write_cable writes them."""
    return {
        s: [swinging_cable(i + (100 if s == "eval" else 0)) for i in range(n)]
        for s, n in SPLITS.items()
    }


def _csv_text(array: np.ndarray) -> str:
    """(frames, 3, V) as a motion-capture CSV, in millimetres."""
    frames, _, v = array.shape
    header = ["frame", "time"] + [f"m{j}_{a}" for j in range(v) for a in "xyz"]
    rows = [",".join(header)]
    for t in range(frames):
        cells = [f"{x * 1000:.9f}" for x in array[t].T.ravel()]
        rows.append(",".join([str(t), f"{t / 100:.2f}", *cells]))
    return "\n".join(rows) + "\n"


def _write(fmt: str, path: Path, name: str, array: np.ndarray) -> None:
    if fmt == "npy":
        np.save(path / f"{name}.npy", array)
    elif fmt == "npy-fv3":
        np.save(path / f"{name}.npy", array.transpose(0, 2, 1))
    elif fmt == "npz":
        np.savez(path / f"{name}.npz", positions=array)
    elif fmt == "h5":
        with h5py.File(path / f"{name}.h5", "w") as f:
            f.create_dataset("positions", data=array)
    elif fmt == "csv":
        (path / f"{name}.csv").write_text(_csv_text(array))


def write_folder(root: Path, fmt: str) -> Path:
    for split, arrays in _recordings().items():
        (root / split).mkdir(parents=True)
        for i, array in enumerate(arrays):
            _write(fmt, root / split, str(i), array)
    return root


@pytest.fixture
def reference(deform_reference: MarkerDataset) -> MarkerDataset:
    return deform_reference


def _same(data: MarkerDataset, reference: MarkerDataset) -> None:
    np.testing.assert_allclose(data.positions, reference.positions, atol=1e-6)
    np.testing.assert_array_equal(data.held, reference.held)
    np.testing.assert_array_equal(data.split, reference.split)
    np.testing.assert_array_equal(data.episode_lengths, reference.episode_lengths)
    assert list(data.names) == list(reference.names)


@pytest.mark.parametrize("fmt", ["npy", "npy-fv3", "npz", "h5", "csv"])
def test_each_format_gives_the_deform_dataset(
    fmt: str, tmp_path: Path, reference: MarkerDataset
) -> None:
    source = write_folder(tmp_path / "CABLE", fmt)
    units = ("--units", "mm") if fmt == "csv" else ()
    assert dlo_import(source, tmp_path / "out", *units) == 0
    _same(load_dataset(tmp_path / "out"), reference)


def test_one_npz_or_h5_file_may_hold_many_trajectories(tmp_path: Path) -> None:
    arrays = _recordings()["train"]
    for split in ("train", "eval"):
        (tmp_path / "C" / split).mkdir(parents=True)
    np.savez(tmp_path / "C" / "train" / "a.npz", **{f"t{i}": a for i, a in enumerate(arrays)})
    with h5py.File(tmp_path / "C" / "eval" / "b.h5", "w") as f:
        f.create_dataset("run/one", data=arrays[0])
        f.create_dataset("run/two", data=arrays[1])
    assert dlo_import(tmp_path / "C", tmp_path / "out") == 0
    data = load_dataset(tmp_path / "out")
    assert data.episode_names("train") == ["a.t0", "a.t1", "a.t2"]
    assert data.episode_names("eval") == ["b.run/one", "b.run/two"]


def test_the_user_names_the_held_markers(tmp_path: Path, capsys) -> None:
    source = write_folder(tmp_path / "C", "npy")
    assert dlo_import(source, tmp_path / "out", "--held", "0,-1") == 0
    assert json.loads(capsys.readouterr().out)["held_markers"] == [0, MARKERS - 1]
    assert dlo_import(source, tmp_path / "o2", "--held", "0,1") == 2
    assert dlo_import(source, tmp_path / "o3", "--held", "0,9") == 2
    assert dlo_import(source, tmp_path / "o4", "--held", ",".join(map(str, range(MARKERS)))) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "one half" in err[0] and "marker 9" in err[1] and "every" in err[2]
    assert not any((tmp_path / o).exists() for o in ("o2", "o3", "o4"))


def test_csv_gaps_are_refused_unless_filled(tmp_path: Path, capsys) -> None:
    source = write_folder(tmp_path / "C", "csv")
    path = source / "train" / "1.csv"
    lines = path.read_text().splitlines()
    for t in (10, 11):  # marker 2 missing in frames 10 and 11 (lines 11 and 12)
        cells = lines[t + 1].split(",")
        cells[2 + 6 : 2 + 9] = ["", "", ""]
        lines[t + 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    assert dlo_import(source, out, "--units", "mm") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "2 gaps" in err and "--fill-gaps 2" in err
    assert not out.exists()
    assert dlo_import(source, out, "--units", "mm", "--fill-gaps", "1") == 2
    assert dlo_import(source, out, "--units", "mm", "--fill-gaps", "2") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["gaps_filled"] == {"train/1": 2}
    truth = swinging_cable(1).transpose(0, 2, 1)
    filled = load_dataset(out).episodes("train")[1]
    np.testing.assert_allclose(filled[10:12, 2], truth[10:12, 2], atol=2e-3)  # linear, smooth


def _csv_edit(edit: Callable[[list[str]], list[str]]) -> Callable[[Path], None]:
    def write(path: Path) -> None:
        text = _csv_text(swinging_cable(7))
        (path / "bad.csv").write_text("\n".join(edit(text.splitlines())) + "\n")

    return write


def _cell(lines: list[str], value: str) -> list[str]:
    cells = lines[5].split(",")
    cells[4] = value
    return [*lines[:5], ",".join(cells), *lines[6:]]


def _h5(path: Path, array: np.ndarray) -> None:
    with h5py.File(path / "bad.h5", "w") as f:
        f.create_dataset("x", data=array)


def _npy(array: np.ndarray) -> Callable[[Path], None]:
    return lambda path: np.save(path / "bad.npy", array)


BAD: dict[str, tuple[Callable[[Path], None], str]] = {
    "wrong shape": (_npy(np.zeros((10, 4, 6))), "shape (10, 4, 6)"),
    "too few markers": (_npy(np.zeros((10, 3, 3))), "at least 4"),
    "NaN": (_npy(np.full((10, 3, 6), np.nan)), "NaN"),
    "text array": (_npy(np.array([["a", "b"]])), "not numbers"),
    "object npy": (_npy(np.array([{}, 1], dtype=object)), "not a readable .npy"),
    "empty npy": (lambda p: (p / "bad.npy").write_bytes(b""), "not a readable .npy"),
    "empty npz": (lambda p: (p / "bad.npz").write_bytes(b""), "not a readable .npz"),
    "empty h5": (lambda p: (p / "bad.h5").write_bytes(b""), "not a readable HDF5"),
    "h5 shape": (lambda p: _h5(p, np.zeros((5, 2))), "expected (frames, 3, markers)"),
    "empty csv": (lambda p: (p / "bad.csv").write_text(""), "is empty"),
    "csv no rows": (_csv_edit(lambda ls: ls[:1]), "0 frames"),
    "csv header": (_csv_edit(lambda ls: ["frame,a,b", *ls[1:]]), "header"),
    "csv text": (_csv_edit(lambda ls: _cell(ls, "abc")), "'abc' is not a number"),
    "csv nan": (_csv_edit(lambda ls: _cell(ls, "nan")), "not a finite number"),
    "ragged csv": (_csv_edit(lambda ls: [*ls[:5], ls[5] + ",1.0", *ls[6:]]), "line 6 has"),
    "csv edge gap": (
        _csv_edit(lambda ls: [ls[0], ls[1].rsplit(",", 1)[0] + ",", *ls[2:]]),
        "first or last frame",
    ),  # fmt: skip
    "unknown suffix": (lambda p: (p / "notes.txt").write_text("hi"), "unknown suffix '.txt'"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_files_get_one_line_and_nothing_is_written(tmp_path: Path, capsys, case) -> None:
    make, words = BAD[case]
    source = write_folder(tmp_path / "C", "npy")
    make(source / "train")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert dlo_import(source, out, "--overwrite") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]


def test_an_array_past_the_budget_is_refused_before_it_is_loaded(tmp_path: Path, capsys) -> None:
    source = write_folder(tmp_path / "C", "npy")
    big = np.lib.format.open_memmap(
        source / "train" / "big.npy", mode="w+", dtype=np.float64, shape=(600_000, 3, 6)
    )
    del big  # sparse on disk: 86 MiB as float64, 172 MiB read
    assert dlo_import(source, tmp_path / "out", "--max-memory-mib", "64") == 2
    assert "--max-memory-mib" in capsys.readouterr().err
    shutil.rmtree(source)


def test_csv_markers_take_any_names_in_column_order(tmp_path: Path) -> None:
    source = write_folder(tmp_path / "C", "npy")
    array = swinging_cable(3)
    names = ["tip", "b", "a", "c", "d", "end"]
    text = _csv_text(array).splitlines()
    text[0] = "time," + ",".join(f"{n}_{a}" for n in names for a in "xyz")
    rows = [line.split(",", 1)[1] for line in text[1:]]  # drop the frame column
    (source / "eval" / "9.csv").write_text("\n".join([text[0], *rows]) + "\n")
    for path in source.glob("*/*.npy"):  # all in mm, as the CSV
        np.save(path, np.load(path) * 1000)
    assert dlo_import(source, tmp_path / "out", "--units", "mm") == 0
    data = load_dataset(tmp_path / "out")
    np.testing.assert_allclose(data.episodes("eval")[-1], array.transpose(0, 2, 1), atol=1e-6)


def test_a_csv_past_the_budget_is_refused_unread(tmp_path: Path, capsys) -> None:
    source = write_folder(tmp_path / "C", "csv")
    (source / "train" / "big.csv").write_bytes(b"frame\n" + b"0\n" * 600_000)
    assert dlo_import(source, tmp_path / "out", "--units", "mm", "--max-memory-mib", "16") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--max-memory-mib" in err, err
