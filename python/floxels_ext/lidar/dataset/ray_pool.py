"""The workers of one Ray job: taken from the warm pool or started, and given back at the end.

The warm pool (``--keep-workers SECONDS``, default 120; 0 turns it off): workers are detached
named actors in the ``floxels`` namespace, named ``w-<key>-<id>`` where the key is a digest of
the package (version and the sizes and times of its files, so an edited checkout never reuses
old code), Ray's and Python's versions and the worker's resources and device. A job first
claims idle workers of its key (``FloxelsWorker.claim``: one job at a time), then starts the
rest; each worker waits ``keep_s`` seconds idle for the next job, then exits and frees its GPU.
A job that starts workers first asks every idle pooled worker it did not claim (other options,
other versions) to exit, so they never hold the resources it waits for. With the pool off,
workers are plain actors of the job (they die with its driver) and are killed at its end.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["NAMESPACE", "Workers", "Slot", "pool_key"]

NAMESPACE = "floxels"
CLAIM_WAIT_S = 2.0  # a pooled worker answers a claim in milliseconds (one handed over: HANDOVER_S)


def _code_stamp() -> str:
    import floxels_ext

    root = Path(floxels_ext.__file__).parent
    h = hashlib.sha1(floxels_ext.__version__.encode())
    for p in sorted(root.rglob("*")):
        if p.suffix in (".py", ".so") and p.is_file():
            st = p.stat()
            h.update(f"{p.relative_to(root)}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()


def pool_key(gpus: float, cpus: float, device: str) -> str:
    """Which pooled workers a job may reuse: same code, Ray, Python, resources and device."""
    import ray

    raw = json.dumps([_code_stamp(), ray.__version__, list(sys.version_info[:2]), gpus, cpus, device])
    return hashlib.sha1(raw.encode()).hexdigest()[:12]


@dataclass
class Slot:
    """One worker of the job."""

    name: str
    actor: object
    pooled: bool
    requested: float                  # time.time() when the driver asked for it (or claimed it)
    claimed: bool = False             # taken warm from the pool
    alive: bool = False               # it has answered a poll
    launched: bool = False            # run() was called
    leases: set = field(default_factory=set)


class Workers:
    """The job's workers (module docstring). ``start(n)`` claims or starts n of them at once
    (before the driver lists the dataset); ``add()`` starts a replacement; ``close(ok)`` gives
    them back: pooled ones stay warm after a job that ended normally, everything else is killed."""

    def __init__(self, ray, gpus: float, cpus: float, device: str, keep_s: float, t0: float) -> None:
        self.ray, self.gpus, self.cpus, self.device = ray, gpus, cpus, device
        self.keep_s = keep_s if keep_s and keep_s > 0 else None
        self.t0 = t0
        self.job = uuid.uuid4().hex[:12]
        self.key = pool_key(gpus, cpus, device) if self.keep_s else None
        self.slots: list[Slot] = []
        self.made = 0
        self.retired = 0
        self.target = 0
        # claim ref -> (name, handle): the pool's workers of this key that did not answer within
        # CLAIM_WAIT_S (still starting, or being handed over): the job runs without them and takes
        # each as its claim answers (take_late), instead of holding its ready workers idle meanwhile
        self.late: dict = {}

    def _options(self, name: str | None):
        from floxels_ext.lidar.dataset.ray_worker import FloxelsWorker

        # threaded: run() holds one thread for the whole job; poll, offer and the pool's calls the others
        opts = dict(num_gpus=self.gpus, num_cpus=self.cpus, max_restarts=0, max_concurrency=8)
        if name is not None:
            opts.update(name=name, namespace=NAMESPACE, lifetime="detached")
        return self.ray.remote(FloxelsWorker).options(**opts)

    def _pooled(self) -> list[str]:
        try:
            return [a["name"] for a in self.ray.util.list_named_actors(all_namespaces=True)
                    if a.get("namespace") == NAMESPACE and a["name"].startswith("w-")]
        except Exception:  # noqa: BLE001 - no pool then; the job starts its own workers
            return []

    def _handle(self, name: str):
        try:
            return self.ray.get_actor(name, namespace=NAMESPACE)
        except ValueError:  # exited since it was listed
            return None

    def _claim(self, names: list[str], n: int) -> list[Slot]:
        """Claims up to n of the pool's workers ``names``; those that do not answer within
        CLAIM_WAIT_S are still starting (a job that ended before they were up started them) or
        being handed over by that job: they go to ``late`` and join the job when their claims
        answer. Neither waiting for them (the 4-GPU job's start held ~7 s, E7) nor starting new
        workers beside them (which would wait for the resources they hold: 4 of 8 workers ~7 s
        late, E6) keeps the ready workers busy."""
        handles = {nm: h for nm in names if (h := self._handle(nm)) is not None}
        refs = {h.claim.remote(self.job): nm for nm, h in handles.items()}
        got: list[Slot] = []
        self._answers(refs, handles, got, n, len(refs), CLAIM_WAIT_S)
        for ref, nm in refs.items():
            self.late[ref] = (nm, handles[nm])
        return got

    def _answers(self, refs: dict, handles: dict, got: list, n: int, k: int, timeout: float) -> None:
        """Waits for k of the claims ``refs`` (at most ``timeout``) and takes the granted ones
        into ``got`` up to n (a surplus one is released); answered claims leave ``refs``."""
        ready, _ = self.ray.wait(list(refs), num_returns=k, timeout=timeout) if k else ([], [])
        for ref in ready:
            nm = refs.pop(ref)
            try:
                ok = self.ray.get(ref)
            except self.ray.exceptions.RayError:
                continue
            if ok and len(got) < n:
                got.append(Slot(nm, handles[nm], True, time.time(), claimed=True))
            elif ok:
                handles[nm].release.remote(self.job)

    def start(self, n: int) -> None:
        self.target = n
        pooled = self._pooled() if self.keep_s else []
        mine = [nm for nm in pooled if nm.startswith(f"w-{self.key}-")]
        self.slots += self._claim(mine, n)
        missing = n - len(self.slots) - len(self.late)  # the late ones are coming
        if missing > 0:
            self._retire_idle({s.name for s in self.slots} | {nm for nm, _ in self.late.values()})
        for _ in range(max(0, missing)):
            self.add()

    def take_late(self, ref) -> Slot | None:
        """The answer of a late claim (``late``): its worker as a slot of the job, or None when it
        was refused, or granted once the job had all its workers (then given back)."""
        nm, handle = self.late.pop(ref)
        try:
            ok = self.ray.get(ref)
        except self.ray.exceptions.RayError:
            return None
        if not ok:
            return None
        if len(self.slots) >= self.target:
            handle.release.remote(self.job)
            return None
        slot = Slot(nm, handle, True, time.time(), claimed=True)
        self.slots.append(slot)
        return slot

    def _retire_idle(self, keep: set[str]) -> None:
        """Idle pooled workers this job does not use exit (they may hold the resources it needs)."""
        for nm in self._pooled():
            if nm not in keep and (h := self._handle(nm)) is not None:
                h.retire.remote()
                self.retired += 1

    def add(self) -> Slot:
        """Starts one more worker (its __init__ and warm-up begin as soon as Ray places it)."""
        self.made += 1
        name = f"w-{self.key}-{uuid.uuid4().hex[:8]}" if self.keep_s else f"worker-{self.made - 1}"
        actor = self._options(name if self.keep_s else None).remote(self.cpus, self.device, self.keep_s, self.job)
        slot = Slot(name, actor, bool(self.keep_s), time.time())
        self.slots.append(slot)
        return slot

    def drop(self, slot: Slot, ok: bool = True) -> None:
        """A worker the job does not need (fewer tasks than workers, or still starting when the
        job is done; ``ok`` False: it failed and is killed)."""
        if slot in self.slots:
            self.slots.remove(slot)
            self._give_back(slot, ok)

    def finished(self, slot: Slot) -> None:
        """Its run returned: a pooled worker has released itself; a job's own is killed now (its
        GPU free at once)."""
        if slot in self.slots:
            self.slots.remove(slot)
            if not slot.pooled:
                self._give_back(slot, ok=False)

    def _give_back(self, slot: Slot, ok: bool) -> None:
        try:
            if slot.pooled and ok and slot.launched:  # its run releases it (one still starting: at once)
                slot.actor.offer.remote(self.job, None)
            elif slot.pooled and ok:  # taken from the pool, or started for this job and not used: to the pool
                # (a short job can end before some of its workers are up: killing them made the next
                # job start them again, ~6 s each; the release waits in the actor's queue for its start)
                slot.actor.release.remote(self.job)
            else:  # failed, or not pooled
                self.ray.kill(slot.actor, no_restart=True)
        except Exception:  # noqa: BLE001 - a dead worker needs nothing
            pass

    def close(self, ok: bool) -> None:
        for slot in self.slots:
            self._give_back(slot, ok)
        self.slots = []
        for nm, handle in self.late.values():  # claims not answered during the job (a short one):
            try:  # the worker refuses the claim if this release reaches it first (FloxelsWorker.release)
                handle.release.remote(self.job)
            except Exception:  # noqa: BLE001 - a dead worker needs nothing
                pass
        self.late = {}
