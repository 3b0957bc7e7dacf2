"""The dispatcher: claims queued jobs under a lease, keeps the lease alive with heartbeats while the
job runs, and puts jobs whose lease expired (a dead dispatcher or worker) back in the queue.

Two ways to run a claimed job:
- embedded (no Ray Jobs address): `execute` in a thread of this process, whose training runs in the
  local Ray's worker processes (`ensure_ray`, called from the main thread); on the local backend
  (`LECO_BACKEND=local`, training in the caller) the attempt runs in a child process instead
  (service/jobs/process.py), so that a run out of memory fails its job and not this process;
- cluster (`LECO_RAY_JOBS_ADDRESS`, e.g. http://ray-head:8265): a Ray job `python -m service.execute
  ...` submitted through the Ray Jobs API with the deterministic submission id
  `leco-job-<id>-attempt-<n>`; the dispatcher follows it and heartbeats. A re-claimed job first
  stops an earlier attempt still running there.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import TYPE_CHECKING

from service import queue
from service.jobs.attempt import execute
from service.jobs.kinds import KINDS
from service.jobs.process import run_in_child
from service.settings import Settings

if TYPE_CHECKING:
    from ray.job_submission import JobStatus, JobSubmissionClient

log = logging.getLogger("leco.dispatcher")

RAY_TERMINAL = ("SUCCEEDED", "FAILED", "STOPPED")


def submission_id(job_id: int, attempt: int) -> str:
    return f"leco-job-{job_id}-attempt-{attempt}"


def cluster_env(s: Settings) -> dict[str, str]:
    """The settings a Ray job's `service.execute` reads: where the data is, and the lease and retry
    budget the dispatcher holds the job under (the run must give up on the database before this
    dispatcher's lease lapses)."""
    return {
        "DATABASE_URL": s.db_url,
        "LECO_DATA_DIR": str(s.data_dir.resolve()),
        "LECO_ARTIFACT_ROOT": str(s.artifacts),
        "LECO_BACKEND": s.backend,
        "LECO_LEASE_S": repr(s.lease_s),
        "LECO_DB_RETRY_S": repr(s.retry_s),
        "LECO_PIXEL_CACHE": str(s.data_dir.resolve() / "pixel-cache"),
        "LECO_RAY_JOBS_ADDRESS": "",
    }  # inside the Ray job, train on the cluster it runs on


class Dispatcher:
    def __init__(
        self, settings: Settings, slots: int = 1, poll_s: float = 1.0, owner: str | None = None
    ):
        self.settings, self.slots, self.poll_s = settings, slots, poll_s
        self.owner = owner or f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.pool = ThreadPoolExecutor(max_workers=slots, thread_name_prefix="leco-job")
        self.running: dict[int, tuple[int, Future]] = {}  # job id -> (attempt, its run)
        self.stopping = threading.Event()

    # ----- the loop
    # ----------------------------------------------------------------------------------
    def tick(self) -> int | None:
        """One round: reap expired leases, then claim a job if a slot is free. Returns the claimed
        job id."""
        for job_id, state in queue.requeue_expired(
            self.settings.db_url, self.settings.max_attempts
        ):
            log.warning("job %s: lease expired, now %s", job_id, state)
        self.running = {j: (a, f) for j, (a, f) in self.running.items() if not f.done()}
        if len(self.running) >= self.slots or self.stopping.is_set():
            return None
        claimed = queue.claim(
            self.settings.db_url,
            self.owner,
            self.settings.lease_s,
            {kind.name: kind.scene_states for kind in KINDS.values()},
        )
        if claimed is None:
            return None
        job_id, attempt = claimed
        log.info("job %s: claimed (attempt %s) by %s", job_id, attempt, self.owner)
        self.running[job_id] = (attempt, self.pool.submit(self.run_job, job_id, attempt))
        return job_id

    def run_forever(self) -> None:
        while not self.stopping.is_set():
            try:
                claimed = self.tick()
            except Exception:  # a database hiccup must not end the dispatcher: log, wait, try again
                log.exception("dispatcher tick failed; retrying")
                claimed = None
            if claimed is None:
                self.stopping.wait(self.poll_s)

    def stop(self, wait: bool = True) -> None:
        self.stopping.set()
        self.pool.shutdown(wait=wait)

    def release_all(self) -> None:
        """Stops claiming and returns every job this dispatcher runs to the queue, for the next
        claim to resume from its last checkpoint. Called first thing on SIGTERM or Ctrl-C (from the
        signal handler), before the local Ray goes down under the run and its error could be taken
        for the job's own failure."""
        self.stopping.set()
        for job_id, (attempt, future) in list(self.running.items()):
            reason = (
                f"attempt {attempt} was interrupted: its dispatcher ({self.owner}) stopped; the "
                "job resumes from its last checkpoint when a dispatcher claims it again"
            )
            try:
                if not future.done() and queue.release(
                    self.settings.db_url, job_id, attempt, reason
                ):
                    log.info("job %s attempt %s: returned to the queue", job_id, attempt)
            # the database is away: the lease expires instead, with the same outcome
            except Exception:
                log.exception("job %s: could not return it to the queue", job_id)

    def shutdown(self, wait_s: float = 20.0) -> None:
        """release_all(), then up to `wait_s` for the runs to checkpoint and stop (they see the job
        queued at their next step boundary)."""
        self.release_all()
        futures = [f for _, f in self.running.values()]
        _, left = wait(futures, timeout=wait_s)
        if left:
            log.warning("%d run(s) still stopping after %.0f s; leaving them", len(left), wait_s)
        self.pool.shutdown(wait=False, cancel_futures=True)

    # ----- one job
    # -----------------------------------------------------------------------------------
    def run_job(self, job_id: int, attempt: int) -> str:
        done = threading.Event()
        beat = threading.Thread(
            target=self._heartbeat,
            args=(job_id, attempt, done),
            daemon=True,
            name=f"leco-lease-{job_id}",
        )
        beat.start()
        try:
            if self.settings.ray_address:
                state = self._run_on_cluster(job_id, attempt, done)
            elif self.settings.backend == "local" and self.settings.local_in_child:
                state = run_in_child(self.settings, job_id, attempt)
            else:
                state = execute(self.settings, job_id, attempt)
            log.info("job %s attempt %s: %s", job_id, attempt, state)
            return state
        except Exception as error:
            log.exception("job %s attempt %s: the dispatcher could not run it", job_id, attempt)
            queue.finish(
                self.settings.db_url, job_id, attempt, "failed", f"{type(error).__name__}: {error}"
            )
            return "failed"
        finally:
            done.set()
            beat.join()

    def _heartbeat(self, job_id: int, attempt: int, done: threading.Event) -> None:
        every = self.settings.lease_s / 4
        while not done.wait(every):
            try:
                if not queue.heartbeat(
                    self.settings.db_url, job_id, attempt, self.owner, self.settings.lease_s
                ):
                    log.warning("job %s attempt %s: lease no longer ours", job_id, attempt)
                    # the run sees it at its next step boundary (DatabaseRunStore.stop_reason)
                    return
            except Exception:  # the database is briefly away: keep trying until the lease runs out
                log.exception("job %s: heartbeat failed", job_id)

    def _run_on_cluster(self, job_id: int, attempt: int, done: threading.Event) -> str:
        from ray.job_submission import JobStatus, JobSubmissionClient

        client = JobSubmissionClient(self.settings.ray_address)
        # an earlier attempt may still be running if only its dispatcher died
        for earlier in range(1, attempt):
            try:
                if client.get_job_status(submission_id(job_id, earlier)) not in RAY_TERMINAL:
                    client.stop_job(submission_id(job_id, earlier))
                    self._wait_terminal(client, submission_id(job_id, earlier), timeout_s=120)
            except RuntimeError:
                pass  # never submitted
        sid = submission_id(job_id, attempt)
        try:
            client.submit_job(
                entrypoint=f"python -m service.execute --job-id {job_id} --attempt {attempt}",
                submission_id=sid,
                runtime_env={"env_vars": cluster_env(self.settings)},
            )
        except RuntimeError as error:
            if "already exists" not in str(error):
                raise  # else: this very attempt was submitted before (a retried tick); follow it
        status = self._wait_terminal(client, sid, timeout_s=None)
        if status != JobStatus.SUCCEEDED:
            logs = client.get_job_logs(sid)[-2000:]
            queue.finish(
                self.settings.db_url,
                job_id,
                attempt,
                "failed",
                f"Ray job {sid} ended {status}: "
                f"{logs.strip().splitlines()[-1] if logs.strip() else ''}",
            )
            return "failed"
        return "succeeded"

    def _wait_terminal(
        self, client: JobSubmissionClient, sid: str, timeout_s: float | None
    ) -> JobStatus:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            status = client.get_job_status(sid)
            if status in RAY_TERMINAL or (deadline is not None and time.monotonic() > deadline):
                return status
            time.sleep(self.poll_s)
