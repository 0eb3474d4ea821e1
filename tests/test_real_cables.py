"""Recorded cables (marker form): `dlo import` of DEFORM-format files, the benchmark
protocol and its references, marker-form training and evaluation, and files that must be
refused. Tiny files of the same format are written here; the real data set is used when
``DLOCLI_DEFORM_DATA`` (or the development checkout's copy) is present."""

from __future__ import annotations

import json
import os
import pickle
from pathlib import Path

import h5py
import numpy as np
import pytest

from dlocli.data import Dataset, MarkerDataset, load_dataset, protocol
from dlocli.recorded_cables import deform
from dlocli.registry import models

from tiny import FRAMES, MARKERS, run_dlo, swinging_cable, write_cable

DEFORM_DATA = Path(
    os.environ.get("DLOCLI_DEFORM_DATA", Path(__file__).parents[2] / "shared/data/deform")
)


def _run(*argv: str) -> int:
    return run_dlo(list(argv))


@pytest.fixture(scope="module")
def cable(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_cable(tmp_path_factory.mktemp("cable") / "CABLE")


@pytest.fixture(scope="module")
def imported(cable: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("imported") / "data"
    assert _run("import", "--source", str(cable), "--out", str(out), "--json") == 0
    return out


def test_import_keeps_the_split_and_the_positions(cable: Path, imported: Path) -> None:
    data = load_dataset(imported)
    assert isinstance(data, MarkerDataset)
    assert data.n_markers == MARKERS and list(np.flatnonzero(data.held)) == [0, 1, 4, 5]
    assert data.episode_names("train") == ["0", "1", "2", "3"]
    assert data.episode_names("eval") == ["0", "1"]
    first = np.asarray(pickle.loads((cable / "eval" / "1.pkl").read_bytes())).transpose(0, 2, 1)
    np.testing.assert_allclose(data.episodes("eval")[1], first, atol=1e-6)


def test_the_freeze_reference_is_the_published_score(imported: Path, cable: Path) -> None:
    """DEFORM's score of freezing the free markers at frame 1, computed here by hand from
    the files: the mean |error| per coordinate over frames 2.., all markers, in cm."""
    summary = json.loads((imported / "summary.json").read_text())
    by_hand = []
    for path in sorted((cable / "eval").glob("*.pkl")):
        rec = np.asarray(pickle.loads(path.read_bytes()))  # (frames, 3, V)
        pred = np.repeat(rec[1:2], len(rec), 0)
        pred[:, :, [0, 1, -2, -1]] = rec[:, :, [0, 1, -2, -1]]
        by_hand.append(np.abs(pred[2:] - rec[2:]).mean() * 100)
    assert summary["eval_freeze_cm"] == pytest.approx(np.mean(by_hand), abs=1e-3)


@pytest.mark.skipif(not (DEFORM_DATA / "DLO1" / "eval").is_dir(), reason="DEFORM data not here")
def test_the_references_on_the_real_cables() -> None:
    """The freeze and straight-line references of the data set's README, ±0.02 cm."""
    published = {"DLO1": (5.673, 6.67), "DLO2": (5.288, 6.38), "DLO3": (4.849, 6.50),
                 "DLO4": (5.299, 6.08)}  # fmt: skip
    for name, (frozen, line) in published.items():
        episodes = [a for _, a in deform.read_folder(DEFORM_DATA / name)["eval"]]
        held = deform.held_markers(episodes[0].shape[1])
        score = {k: np.mean([protocol.deform_score_cm(ref(e, held), e) for e in episodes])
                 for k, ref in protocol.REFERENCES.items()}  # fmt: skip
        assert score["freeze"] == pytest.approx(frozen, abs=0.02), name
        assert score["straight_line"] == pytest.approx(line, abs=0.02), name


def test_train_and_evaluate_by_the_protocol(imported: Path, tmp_path: Path) -> None:
    """Three commands: import (above), train through rollouts, evaluate on the eval split.
    A model trained through 8-step rollouts beats freezing the cable on this smooth motion."""
    model = tmp_path / "model"
    args = ["--data", str(imported), "--out", str(model), "--update-steps", "150",
            "--rollout-steps", "8", "--lr", "3e-3", "--hidden", "16", "--device", "cpu",
            "--val-fraction", "0.25", "--json"]  # fmt: skip
    assert _run("train", *args) == 0
    summary = json.loads((model / "summary.json").read_text())
    assert summary["form"] == "markers" and summary["val_episodes"] == 1
    plot = tmp_path / "horizon.png"
    assert _run("eval", "--checkpoint", str(model), "--data", str(imported),
                "--out", str(tmp_path / "eval"), "--plot", str(plot), "--json") == 0  # fmt: skip
    result = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert result["episodes"] == 2 and len(result["model_scores_cm"]) == 2
    assert result["model_score_cm"] < result["freeze_score_cm"]
    assert result["ms_per_step_1_thread"] > 0 and plot.stat().st_size > 0
    curves = json.loads((tmp_path / "eval" / "error_by_frame.json").read_text())
    assert set(curves["free_error_mm"]) == {"model", "freeze", "straight_line"}
    assert len(curves["abs_error_cm"]["model"]) == FRAMES


def _trained(run: Path) -> tuple[dict, list[list[str]], dict]:
    """A marker run's final weights, metrics rows without their seconds, and summary without
    its seconds and run directory."""
    from dlocli.models.checkpoints import read_checkpoint

    weights = read_checkpoint(run / "checkpoints" / "final.pt")["state_dict"]
    rows = [line.split(",")[:-1] for line in (run / "metrics.csv").read_text().splitlines()]
    summary = json.loads((run / "summary.json").read_text())
    return weights, rows, {k: v for k, v in summary.items() if k not in ("seconds", "out")}


@pytest.mark.parametrize("fine_tune", [None, "all"])
def test_a_stopped_marker_run_resumes_to_the_same_bits(
    imported: Path, tmp_path: Path, fine_tune: str | None
) -> None:
    """`dlo train` on a marker dataset, cancelled after its second validation (of three) and
    resumed from checkpoints/last.pt, ends bit-identical to the run never stopped: every
    weight, every metrics value but the seconds, the summary; fresh and fine-tuning alike. An
    ensemble's run refuses to resume, in one line."""
    import torch

    from dlocli.cancel import CancelToken
    from dlocli.errors import BadInput
    from dlocli.models.checkpoints import read_checkpoint
    from dlocli.models.fit import ENSEMBLE_DOES_NOT_RESUME
    from dlocli.models.fitting import RolloutValidated
    from dlocli.models.spec import TrainSpec
    from dlocli.runs.train import resumed_spec, run_training

    spec = TrainSpec(data=[imported], model={"name": "mlp", "hidden": 16}, update_steps=9,
                     eval_every=3, rollout_steps=4, lr=3e-3, batch_size=8, device="cpu",
                     val_fraction=0.25)  # fmt: skip
    if fine_tune is not None:
        run_training(spec.model_copy(update={"out": tmp_path / "start", "update_steps": 3}))
        spec = spec.model_copy(update={"init_from": tmp_path / "start", "fine_tune": fine_tune,
                                       "seed": 1})  # fmt: skip
    run_training(spec.model_copy(update={"out": tmp_path / "whole"}))

    token, seen = CancelToken(), []

    def stop_after_step_6(event) -> None:
        seen.append(event.values.get("step"))
        if isinstance(event, RolloutValidated) and event.done == 6:
            token.cancel()

    stopped = tmp_path / "stopped"
    with pytest.raises(KeyboardInterrupt):
        run_training(spec.model_copy(update={"out": stopped}), progress=stop_after_step_6,
                     cancel=token)  # fmt: skip
    assert max(s for s in seen if s is not None) == 6, "a step after the stop was taken"
    assert not (stopped / "checkpoints" / "final.pt").exists()
    last = read_checkpoint(stopped / "checkpoints" / "last.pt")
    assert last["step"] == 6 and len(last["history"]) == 2 + (fine_tune is not None)
    went_on: list = []
    resumed = run_training(resumed_spec(stopped, {}), resume=True, progress=went_on.append)
    assert went_on[0].done == 6 and min(e.values.get("step", 9) for e in went_on) == 7
    assert resumed["update_steps"] == 9

    whole, again = _trained(tmp_path / "whole"), _trained(stopped)
    assert whole[0].keys() == again[0].keys()
    assert all(torch.equal(v, again[0][k]) for k, v in whole[0].items())
    assert whole[1] == again[1] and len(whole[1]) == 1 + 3 + (fine_tune is not None)
    assert whole[2] == again[2]

    members = spec.model.model_copy(update={"members": 2})
    with pytest.raises(BadInput) as refused:
        run_training(spec.model_copy(update={"out": stopped, "model": members}), resume=True)
    assert str(refused.value) == ENSEMBLE_DOES_NOT_RESUME


@pytest.mark.parametrize("name", models.names())
def test_every_registered_model_works_in_the_marker_view(name: str) -> None:
    import torch

    from dlocli.models.marker_model import build_marker_model

    held = deform.held_markers(MARKERS)
    model = build_marker_model({"name": name, "hidden": 8}, MARKERS, held)
    rec = torch.as_tensor(swinging_cable(0).transpose(0, 2, 1)[None], dtype=torch.float32)
    pred = model.rollout(rec[:, 1], rec[:, 0], rec[:, 2:])
    assert pred.shape == rec[:, 2:].shape
    torch.testing.assert_close(pred[:, :, held], rec[:, 2:, held])  # held ones are the input


def test_a_crafted_pickle_is_refused_and_runs_nothing(tmp_path: Path, capsys) -> None:
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    root = write_cable(tmp_path / "CABLE")
    (root / "train" / "evil.pkl").write_bytes(pickle.dumps(Payload()))
    code = _run("import", "--source", str(root), "--out", str(tmp_path / "out"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and not marker.exists() and not (tmp_path / "out").exists()
    assert len(err.splitlines()) == 1 and "never run" in err and "posix.system" in err


@pytest.mark.parametrize(
    "bad, words",
    [
        (lambda: [[1.0, 2.0], [3.0]], "rectangular"),
        (lambda: np.zeros((10, 4, 6)).tolist(), "shape"),
        (lambda: np.zeros((10, 3, 3)).tolist(), "at least 4"),
        (lambda: np.full((10, 3, 6), np.nan).tolist(), "NaN"),
        (lambda: "text", "holds text"),
    ],
)
def test_bad_files_get_one_line(tmp_path: Path, capsys, bad, words: str) -> None:
    root = write_cable(tmp_path / "CABLE")
    (root / "train" / "bad.pkl").write_bytes(pickle.dumps(bad()))
    existing = tmp_path / "out"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    assert _run("import", "--source", str(root), "--out", str(existing), "--overwrite") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]


def test_mixed_marker_counts_are_refused(tmp_path: Path, capsys) -> None:
    root = write_cable(tmp_path / "CABLE")
    (root / "eval" / "z.pkl").write_bytes(pickle.dumps(swinging_cable(0, markers=7).tolist()))
    assert _run("import", "--source", str(root), "--out", str(tmp_path / "out")) == 2
    assert "mixed marker counts" in capsys.readouterr().err


def test_rollout_training_is_refused_for_rod_data(
    small_dataset_dir: Path, tmp_path: Path, capsys
) -> None:
    args = ["--data", str(small_dataset_dir), "--rollout-steps", "4", "--out", str(tmp_path / "m")]
    assert _run("train", *args) == 2
    assert "marker datasets" in capsys.readouterr().err


def test_version_1_rod_datasets_still_load(small_dataset_dir: Path, tmp_path: Path) -> None:
    old = tmp_path / "v1.h5"
    old.write_bytes((small_dataset_dir / "dataset.h5").read_bytes())
    with h5py.File(old, "r+") as f:
        f.attrs["format_version"] = 1
        del f.attrs["form"]
    assert isinstance(load_dataset(old), Dataset)


def test_the_length_projection_keeps_held_markers_and_restores_lengths() -> None:
    """The compiled loop (no gradient, CPU) and the tensor form (training) agree; held
    markers stay; the neighbour distances come back to the requested ones."""
    import torch

    from dlocli.models.marker_model import neighbour_distances, project_lengths

    gen = torch.Generator().manual_seed(0)
    x = torch.randn(3, 12, 3, generator=gen)
    lengths, held = neighbour_distances(x), torch.as_tensor(deform.held_markers(12))
    moved = x + 0.02 * torch.randn(x.shape, generator=gen)
    moved[:, held] = x[:, held]
    before = (neighbour_distances(moved) - lengths).abs().max()
    tensor_form = project_lengths(moved.requires_grad_(True), lengths, held, 10)
    with torch.no_grad():
        compiled = project_lengths(moved, lengths, held, 10)
    torch.testing.assert_close(compiled, tensor_form.detach(), atol=1e-5, rtol=0)
    torch.testing.assert_close(compiled[:, held], x[:, held])
    assert (neighbour_distances(compiled) - lengths).abs().max() < 0.01 * before
