"""Online model learning with MPC: the paper's Algorithm 1 (``dlo online``).

    D <- initial random transitions
    for k = 1..K:
        update the model on D for E epochs (continuing from the previous weights, input noise)
        for j = 1..N: run a trial of T steps from a random start with MPC through the model;
                      with probability p add action noise a ~ A_noise; append (s, a, s') to D

Run directory (every file written atomically)::

    spec.json                      resolved OnlineSpec
    data/initial.h5                the initial random dataset
    data/iter_KK/trial_JJJ.h5      one file per finished trial: the dataset grows atomically
    checkpoints/iter_KK.pt         the model after iteration KK's training (+ Adam state)
    checkpoints/final.pt           the last iteration's model
    references.json                the references (doing nothing, random, held-end) from each start
    metrics.csv                    iteration, trial, transitions, cumulative_reward, ...
    summary.json, plots/learning_curve.png

Resume (``--resume RUN``): an iteration whose checkpoint exists is not retrained; a trial
whose file exists is not rerun. Every random stream is derived from (seed, iteration, trial),
so a resumed run reproduces an uninterrupted one with the same seed.

Where trials run (:mod:`dlocli.executors`): in this process, a pool of local processes
(``workers``), or Ray tasks on a cluster (``executor``, ``ray_address``). Each trial gets the
model's checkpoint as bytes, loaded in memory, and one thread (``threads``: more), and
returns its episode: this process (the driver) writes every file, keeps D in memory and
updates the model (on ``fit.device``; Ray's trials plan on their CPUs), so a cluster needs no
shared file system, and the same seed gives the same trials on any executor. Executor and
workers may change on resume.

Modules: :mod:`~dlocli.runs.online.spec` (the spec, seed streams, file layout),
:mod:`~dlocli.runs.online.trials` (the jobs executors run), :mod:`~dlocli.runs.online.loop`
(the algorithm), :mod:`~dlocli.runs.online.results` (metrics, curve, summary) and
:mod:`~dlocli.runs.online.run` (start and resume).
"""

from dlocli.runs.online.loop import OnlineRun
from dlocli.runs.online.results import iteration_curve
from dlocli.runs.online.run import resume_online, start_online
from dlocli.runs.online.spec import TRAIN, OnlineSpec, RunLayout
from dlocli.runs.online.trials import random_data_episode

__all__ = [
    "TRAIN",
    "OnlineRun",
    "OnlineSpec",
    "RunLayout",
    "iteration_curve",
    "random_data_episode",
    "resume_online",
    "start_online",
]
