#!/usr/bin/env bash
# Calibrate the simulated rod to each DEFORM cable (MuJoCo; PyBullet on DLO3); the runs stay in
# RUNS (outside the repository), each fit's calibrated.yaml and report.json are kept here. Usage:
#   DEFORM=/path/to/DEFORM/data_set examples/calibration/run.sh [runs/calibration]
# One cable at a time, two replay workers each. What was run for the committed results of
# the composite cable (results/CABLE-mujoco; a 2-core machine shared with other jobs), in a
# MuJoCo 3.17.0 venv (as .ci/mujoco3 builds it):
#   examples/calibration/run.sh runs/calibration
#   python examples/calibration/replay_choices.py $DEFORM/DLO3 0.998 0.0968 \
#     examples/calibration/results/replay_choices_DLO3.json
#   python examples/calibration/table.py > examples/calibration/results/summary.md
# The flex rod (MuJoCo 4's rod, results/CABLE-mujoco-flex), in a MuJoCo 4.0.1 venv (the
# constraints' pin), one worker each, and both fits' swing decays, each backend in its own venv:
#   BACKENDS=mujoco-flex WORKERS=1 examples/calibration/run.sh runs/calibration
#   R=examples/calibration/results
#   python examples/calibration/swing_decay.py $R/swing_decay_mujoco-flex.json \
#     $R/DLO{1,2,3,4}-mujoco-flex        # MuJoCo 4
#   python examples/calibration/swing_decay.py $R/swing_decay_mujoco.json \
#     $R/DLO{1,2,3,4}-mujoco             # MuJoCo 3.17
#   python examples/calibration/swing_decay.py $R/swing_sweep_mujoco-flex.json \
#     bending_damping=0.02,0.05,0.1,0.5 $R/DLO3-mujoco-flex   # and the same for DLO3-mujoco
# The real cables' swing against both fits' (results/real_swing.{json,md}): each fit replays
# every recording (CABLE-mujoco in MuJoCo 3, CABLE-mujoco-flex in MuJoCo 4), DLO3-mujoco also
# at bending_damping=0.02 and 0.5, then
#   python examples/calibration/real_swing.py replay $DEFORM/DLO3 $HERE/DLO3.yaml \
#     $R/DLO3-mujoco runs/real_swing [bending_damping=0.02]          # and so on
#   python examples/calibration/real_swing.py analyse $DEFORM runs/real_swing $R/real_swing.json
# DLO3's flex variants (results/flex_variants/): a copy of its run resumed with --generations 10
# --workers 2, and a fit with --parameters young_bending,bending_damping,air_damping,twist_damping
# DLO2's and DLO3's (flex_variants/notes.md; DLO1's and DLO4's nu049 the same, CABLES="DLO1 DLO4"),
# BACKENDS=mujoco-flex WORKERS=1 CABLES="DLO2 DLO3":
# CABLE-mujoco-flex-poisson with --parameters young_bending,bending_damping,air_damping,poisson;
# CABLE-mujoco-flex-nu049 with `backend: {rod: {poisson: 0.49}}` added to the cable's YAML (and
# CABLE-mujoco-nu049 the same with BACKENDS=mujoco WORKERS=1); and
#   python examples/calibration/relative_damping_probe.py $DEFORM/DLO2 0,0.5,2,8
# The earlier rod's (results/rigid/: each YAML with `backend: {rod: {clamp_compliance: rigid}}`,
# train_trajectories 4, generations 3 and no rod_length) and its sim-to-real study:
#   for c in DLO1 DLO2 DLO3 DLO4; do python examples/calibration/sim_to_real.py \
#     runs/calibration/$c-mujoco runs/real/$c/data runs/real/$c runs/sim_to_real/$c; done
#   python examples/calibration/table.py examples/calibration/results/rigid runs/calibration \
#     > examples/calibration/results/rigid/summary.md
# (the variants' and the earlier rod's fits stay in their runs: notes.md and rigid/summary.md)
set -euo pipefail
DEFORM=${DEFORM:?set DEFORM to the folder holding DLO1 ... DLO4}
RUNS=${1:-runs/calibration}
HERE=$(dirname "$0")
CABLES=${CABLES:-DLO1 DLO2 DLO3 DLO4}
BACKENDS=${BACKENDS:-mujoco}
for b in $BACKENDS; do
  for c in $CABLES; do
    run="$RUNS/$c-$b"
    [ -f "$run/report.json" ] || dlo calibrate --spec "$HERE/$c.yaml" --source "$DEFORM/$c" \
      --backend "$b" --workers "${WORKERS:-2}" ${GENERATIONS:+--generations "$GENERATIONS"} \
      --out "$run" --overwrite --json > /dev/null
    mkdir -p "$HERE/results/$c-$b"
    cp "$run/report.json" "$run/calibrated.yaml" "$HERE/results/$c-$b/"
    python -c "import json;r=json.load(open('$run/report.json'));print('$c $b', r['eval_default_cm'], '->', r['eval_calibrated_cm'], 'cm in', r['fit_seconds'], 's')"
  done
done
