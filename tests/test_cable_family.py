"""`dlo family`: many simulated cables from calibrated rods, driven by a recorded cable's
held-marker motion (here one `dlo sample cable` simulates), on the real MuJoCo: each is a
marker dataset `dlo train` takes beside a recorded cable's; the materials lie in the widened
span of the calibrated ones and the same seed draws the same; bad input is one line, exit 2,
nothing written."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from dlocli.calibration.family import (
    BOUNDS,
    DRAWN,
    draw_materials,
    keeps_dataset,
    material_span,
    read_rods,
    run_family,
)
from dlocli.calibration.spec import FamilySpec
from dlocli.cancel import CancelToken
from dlocli.data import MarkerDataset, load_dataset
from dlocli.events import Event

from tiny import MUJOCO_ROD, run_dlo

#: two calibrated rods of few segments: their materials span the family's draw
RODS = {
    "soft": {"density": 400.0, "young_bending": 1e6, "bending_damping": 0.3, "air_damping": 0.02},
    "stiff": {"density": 1200.0, "young_bending": 1e7, "bending_damping": 0.5,
              "air_damping": 0.05},
}  # fmt: skip
SMALL = ["--cables", "2", "--train", "2", "--eval", "1"]


def write_rod(path: Path, material: dict, name: str = MUJOCO_ROD) -> Path:
    rod = {"length": 1.0, "n_segments": 12, "radius": 0.005, **material}
    path.write_text(yaml.safe_dump({"backend": {"name": name, "rod": rod}}))
    return path


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> Path:
    """A sampled recorded cable (imported too), two calibrated rods, and a family of two."""
    root = tmp_path_factory.mktemp("family")
    flags = ["--train", "2", "--eval", "1", "--seconds", "0.4", "--seed", "1"]
    assert run_dlo(["sample", "cable", *flags, "--out", str(root / "cable")]) == 0
    assert run_dlo(["import", "--source", str(root / "cable"), "--out", str(root / "real")]) == 0
    rods = [write_rod(root / f"{n}.yaml", m) for n, m in RODS.items()]
    argv = ["family", "--calibrated", str(rods[0]), "--calibrated", str(rods[1]), "--source",
            str(root / "cable"), *SMALL, "--out", str(root / "family"), "--json"]  # fmt: skip
    assert run_dlo(argv) == 0
    return root


def test_each_cable_is_a_marker_dataset_of_a_material_in_the_widened_span(made: Path) -> None:
    summary = json.loads((made / "family" / "summary.json").read_text())
    assert summary["cables"] == summary["datasets"] == 2
    [source] = summary["sources"]
    assert source["markers"] == 12 and source["source"] == str(made / "cable")
    real = load_dataset(made / "real")
    for row in summary["rows"]:
        data = load_dataset(made / "family" / row["cable"])
        assert isinstance(data, MarkerDataset) and data.n_markers == 12
        assert np.array_equal(data.held, real.held) and data.rate_hz == real.rate_hz
        assert len(data.episodes("train")) == row["train_trajectories"] >= 1
        assert len(data.episodes("eval")) == row["eval_trajectories"]
        kept = row["train_trajectories"] + row["eval_trajectories"]
        assert kept + row["dropped_diverged"] == 3  # a draw that diverged is dropped, counted
        assert data.attrs["material"]["young_bending"] == row["young_bending"]
        for name in DRAWN:  # widen 2: the smallest / 2 to the largest * 2, as simulated
            low, high = min(m[name] for m in RODS.values()), max(m[name] for m in RODS.values())
            floor, ceiling = BOUNDS[name]
            assert max(low / 2, floor) <= row[name] <= min(high * 2, ceiling), (name, row)
        assert 0.8 <= row["length_scale"] <= 1.2
        assert row["length"] == pytest.approx(source["rod_length"] * row["length_scale"])
        free = data.episodes("train")[0][:, ~data.held]
        assert np.isfinite(free).all() and np.ptp(free, axis=0).max() > 1e-3  # it moved
        rod = yaml.safe_load((made / "family" / row["cable"] / "rod.yaml").read_text())
        assert rod["backend"]["rod"]["density"] == pytest.approx(row["density"])
    spec = json.loads((made / "family" / "spec.json").read_text())
    assert spec["cables"] == 2 and spec["widen"] == 2.0


def test_a_cable_is_written_with_enough_trajectories_for_dlo_train_to_validate() -> None:
    """A draw that diverged on all but one of its trajectories leaves a dataset `dlo train`
    refuses (it holds a trajectory out for validation): not written, unless one was asked."""
    assert [keeps_dataset(k, 8) for k in (0, 1, 2, 8)] == [False, False, True, True]
    assert keeps_dataset(1, 1) and not keeps_dataset(0, 1)


def test_the_same_seed_draws_the_same_materials(made: Path) -> None:
    rods = read_rods([made / "soft.yaml", made / "stiff.yaml"])

    def drawn(seed: int) -> list[dict]:
        spec = FamilySpec(cables=5, seed=seed)
        return draw_materials(spec, material_span(rods, spec.widen), [1.0])

    assert drawn(3) == drawn(3) != drawn(4)
    rows = json.loads((made / "family" / "summary.json").read_text())["rows"]
    again = draw_materials(FamilySpec(cables=2), material_span(rods, 2.0), [1.0])
    assert [r["young_bending"] for r in rows] == [a["young_bending"] for a in again]
    assert all(math.isfinite(v) for row in drawn(3) for v in row.values())


def test_several_sources_drive_the_cables_in_turn_each_its_own_rod(made, tmp_path) -> None:
    """Cable k is driven by source k mod 2 (the sampled cable's folder, then its import),
    its rod that source's given length times its factor."""
    sources = ["--source", str(made / "cable"), "--source", str(made / "real")]
    argv = ["family", "--calibrated", str(made / "soft.yaml"), *sources, "--rod-length",
            "0.9,1.1", "--cables", "3", "--train", "1", "--eval", "0", "--out",
            str(tmp_path / "out")]  # fmt: skip
    assert run_dlo(argv) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert [s["rod_length"] for s in summary["sources"]] == [0.9, 1.1]
    driven = [(made / "cable", 0.9), (made / "real", 1.1), (made / "cable", 0.9)]
    for row, (source, length) in zip(summary["rows"], driven, strict=True):
        assert row["source"] == str(source)
        assert row["length"] == pytest.approx(length * row["length_scale"])
        data = load_dataset(tmp_path / "out" / row["cable"])
        assert data.attrs["source"] == str(source)


def test_a_spec_with_one_source_reads_as_before(made: Path) -> None:
    spec = FamilySpec.model_validate({"source": str(made / "cable"), "rod_length": 1.0})
    assert spec.source == [made / "cable"] and spec.rod_length == [1.0]


def test_dlo_train_takes_a_recorded_cable_and_a_simulated_one_together(made: Path) -> None:
    out = made / "trained"
    small = ["--model", "mlp", "--cable-code", "4", "--update-steps", "10", "--rollout-steps",
             "2", "--hidden", "16", "--eval-every", "5", "--device", "cpu"]  # fmt: skip
    data = ["--data", str(made / "real"), "--data", str(made / "family" / "sim-000")]
    argv = ["train", *data, *small, "--out", str(out)]
    assert run_dlo(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [c["data"] for c in summary["cables"]] == [str(made / "real"),
                                                      str(made / "family" / "sim-000")]  # fmt: skip


@pytest.mark.parametrize(
    ("case", "says"),
    [
        ("not-a-rod", "no backend rod"),
        ("unknown-backend", "fish"),
        ("no-rods", "--calibrated"),
        ("no-source", "no recordings"),
        ("empty-source", "holds no"),
        ("cables-0", "cables"),
        ("widen-0.5", "widen"),
        ("widen-nan", "widen"),
        ("length-scale", "--length-scale"),
        ("lengths", "one length per --source"),
        ("length-nan", "rod_length"),
        ("length-4", "at most 3"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(made, tmp_path, capsys, case, says) -> None:
    rod = str(made / "soft.yaml")
    source = ["--source", str(made / "cable")]
    argv = {
        "not-a-rod": ["--calibrated", str(tmp_path / "x.yaml"), *source],
        "unknown-backend": ["--calibrated", str(tmp_path / "f.yaml"), *source],
        "no-rods": source,
        "no-source": ["--calibrated", rod],
        "empty-source": ["--calibrated", rod, "--source", str(tmp_path / "empty")],
        "cables-0": ["--calibrated", rod, *source, "--cables", "0"],
        "widen-0.5": ["--calibrated", rod, *source, "--widen", "0.5"],
        "widen-nan": ["--calibrated", rod, *source, "--widen", "nan"],
        "length-scale": ["--calibrated", rod, *source, "--length-scale", "1.2,0.8"],
        "lengths": ["--calibrated", rod, *source, "--rod-length", "0.9,1.1"],
        "length-nan": ["--calibrated", rod, *source, "--rod-length", "nan"],
        "length-4": ["--calibrated", rod, *source, "--rod-length", "4"],
    }[case]
    (tmp_path / "x.yaml").write_text("hello: 1\n")
    write_rod(tmp_path / "f.yaml", {}, "fish")
    (tmp_path / "empty").mkdir()
    capsys.readouterr()
    assert run_dlo(["family", *argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and says in err[0], err
    assert not (tmp_path / "out").exists()


def test_a_full_folder_needs_overwrite_and_keeps_others_files(made, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    argv = ["family", "--calibrated", str(made / "soft.yaml"), "--source", str(made / "cable"),
            "--cables", "2", "--train", "1", "--eval", "0", "--out", str(out)]  # fmt: skip
    assert run_dlo(argv) == 0
    assert run_dlo(argv) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert run_dlo([*argv[:-3], "1", "--eval", "0", "--cables", "1", "--out", str(out),
                    "--overwrite"]) == 0  # fmt: skip
    names = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert names == ["sim-000", "spec.json", "summary.json"]
    (out / "mine.txt").write_text("keep")
    assert run_dlo([*argv, "--overwrite"]) == 2
    assert (out / "mine.txt").read_text() == "keep"


def test_a_stop_keeps_the_cables_finished(made: Path, tmp_path: Path) -> None:
    """Stopped as the second cable's last trajectory ends: the two finished are kept, with a
    summary saying so, and the third is not begun."""
    token, events = CancelToken(), []

    def progress(event: Event) -> None:
        events.append(event)
        if event.values.get("cable") == "sim-001":
            token.cancel()

    spec = FamilySpec(calibrated=[made / "soft.yaml"], source=made / "cable", cables=3,
                      train=1, eval=0, out=tmp_path / "out")  # fmt: skip
    with pytest.raises(KeyboardInterrupt):
        run_family(spec, progress=progress, cancel=token)
    assert events[0].total == 3 and [e.done for e in events[1:]] == [1, 2]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["stopped"] == "KeyboardInterrupt" and summary["cables"] == 2
    assert load_dataset(tmp_path / "out" / "sim-001").n_episodes == 1
    assert not (tmp_path / "out" / "sim-002").exists()
