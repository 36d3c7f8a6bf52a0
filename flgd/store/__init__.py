"""Persistence of what the cell has experienced: replay transitions, the action log, checkpoints.

Why SQLite in WAL mode: a cycle's outcome is written as one transaction (the
action-log row, the transition and any new heightmap), so a process killed at
any instant leaves either the whole outcome or none of it, and readers
(``flgctl stats``) never block the writer; a cycle that moves the cell first
commits its intent (below).  ``synchronous=FULL``: a commit is on disk when it
returns (one fsync of the WAL per commit, two per cycle that moves, small next
to a cycle's controller time, BENCHMARKS.md "Controller overhead"), so a power
cut loses at most the outcome of the cycle in flight, as a killed process does;
with NORMAL it could also lose the last few committed cycles.

Schema (``SCHEMA_VERSION`` 5), file ``<state_dir>/flgd.sqlite``:

* ``states(id, rows, cols, color, height)`` -- one heightmap pair per row,
  zlib-compressed; colour HxWx3 uint8, height as uint16 in units of
  ``HEIGHT_QUANTUM`` (0.1 mm).  Each state is stored once: the next state of a
  transition is the state of the following one.
* ``transitions(id, step, state_id, next_state_id, primitive, row, col,
  rotation, rotations, reward, done, priority)`` -- the replay buffer.
* ``actions(step PRIMARY KEY, time, backend, outcome, primitive, kind, row,
  col, rotation, reward, success, mu, eta, rule, epsilon, q_value, refused,
  failure, contact_stop_mm, done, duration, t_capture, t_perceive, t_decide, t_plan, t_execute,
  t_judge, t_store, transition_id, policy, cell_time, gripper_time, decide_hidden)`` -- one row per cycle,
  whatever happened;
  ``policy`` is the gate's id of the policy whose greedy decision it was (NULL for an
  epsilon-random action or before the gate); ``duration`` and ``t_*`` are seconds of the
  controller's wall clock, ``cell_time`` the seconds the cycle's plans took on the cell's own
  clock (the UR controller's, or simulated time): the cycle a real arm would take, whatever
  the load on the PC that emulates or simulates it; ``gripper_time`` the part of it the
  gripper's commands and width readings took (the rest is the arm's motion); ``decide_hidden``
  the seconds of the row's decision made while the arm placed the pick before (``t_decide`` is
  then the whole decision, and its time is in the earlier row's ``t_execute``).
  ``t_store`` of a row is written with the next write of a cycle (its intent or
  its commit: a commit cannot time itself).
* ``events(id, time, kind, message)`` -- state changes, faults, policy loads.
* ``counters(name PRIMARY KEY, value)`` -- e.g. learner updates.
* ``meta(key PRIMARY KEY, value)`` -- schema version.
* ``policies(id, created, role, file, sha256, origin, predecessor, learner_updates,
  training_steps, since_step, record)`` and ``gate_events(id, time, step, kind, policy,
  other, who, message, evidence)`` -- the champion/challenger gate's policies (files in
  ``<state_dir>/gate``) and every promotion, drop, rollback and manual override
  (flgd/gate/keeper.py).

A version-1 to -4 store is upgraded in place when it is opened: the missing columns
(``contact_stop_mm``, ``policy``, ``cell_time``, ``gripper_time``, ``decide_hidden``) are added (empty for the old rows) and nothing else changes.

Write-ahead action log: a decided action that will move the cell is recorded
(``record_intent``: its row with outcome ``pending`` -- step, time, action,
plan kind, rule, policy) in its own transaction *before* the cell is told to
move, and completed (``commit_cycle``: outcome, reward, transition) after.  So a
``kill -9``, a power cut or a full disk at any instant leaves every motion in
the log: a row still ``pending`` when the store is next opened, or when a later
cycle is written, becomes ``interrupted`` (its ``failure`` says so).  Neither
outcome is ``executed`` or ``refused``, so stats and the gate's tallies never
count such a row as an outcome; ``flgctl stats`` shows it under "other".

Retention and the disk budget (flgd/disk_budget.py):

* ``keep_transitions`` (the daemon passes the replay capacity): only the newest
  transitions and their states are kept.
* ``max_bytes`` (``storage.max_bytes``): the database and its write-ahead log
  stay under it; above it the oldest transitions and their states are deleted
  first (the newest one is always kept), and the write-ahead log is truncated
  after each checkpoint to fit.  The file keeps its largest size: freed pages
  are reused, not returned to the filesystem.
* ``action_log_days`` (``storage.action_log_days``, 0 = forever): older
  action-log rows are deleted, except the newest row (the step counter is
  ``max(step) + 1``) and the rows the gate's acting policies are tallied from
  (``policies.since_step`` of the champion and challenger).  Each deleted row is
  counted in the ``actions_deleted`` counter.  Events and counters are kept whole.
* ``min_free_bytes`` (``storage.min_free_bytes``): ``check_space`` raises a
  StoreError naming the directory, the free bytes and the floor when the
  filesystem has less, is read-only, or the directory is not writable; the
  cycle calls it before any motion.

The first storage failure is kept as the diagnosis until a write succeeds
again: SQLite reports later failures of the same broken disk differently (after
an I/O error, "database disk image is malformed" although the file is intact),
so those are appended to the first cause instead of replacing it.

The step counter is not stored separately: it is ``max(actions.step) + 1``, so
it can never disagree with the log.

Policy checkpoints are files in ``<state_dir>/checkpoints`` written atomically
by ``flgd.learning.policy_file.save_policy``; the last ``keep`` are kept.

The package, by responsibility: ``database`` (``Store``: opening, the write
transaction, failures and their diagnosis, the cycle's writes and the reads),
``schema`` (the tables, ``SCHEMA_VERSION`` and the upgrade), ``replay_rows``
(heightmaps and transitions as rows), ``action_log`` (the write-ahead rows),
``retention`` (pruning, eviction and the action log's retention inside a
transaction), ``errors`` (``StoreError`` and the operator's sentence) and
``checkpoints`` (``CheckpointDir``).
"""

from __future__ import annotations

from flgd.store.action_log import INTENT_OUTCOME, INTERRUPTED_OUTCOME
from flgd.store.checkpoints import CheckpointDir
from flgd.store.database import Store
from flgd.store.errors import StoreError
from flgd.store.replay_rows import HEIGHT_QUANTUM, StoredTransition, decode_heightmaps, encode_heightmaps
from flgd.store.retention import DELETED_TOTALS
from flgd.store.schema import ACTION_COLUMNS, DB_NAME, SCHEMA_VERSION, TIMING_PHASES

__all__ = [
    "SCHEMA_VERSION",
    "HEIGHT_QUANTUM",
    "StoreError",
    "StoredTransition",
    "Store",
    "CheckpointDir",
    "ACTION_COLUMNS",
    "TIMING_PHASES",
    "INTENT_OUTCOME",
    "INTERRUPTED_OUTCOME",
    "DELETED_TOTALS",
    "DB_NAME",
    "encode_heightmaps",
    "decode_heightmaps",
]
