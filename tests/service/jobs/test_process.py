"""On the local backend a job's attempt runs in a child process of the dispatcher: killed as the
kernel's out-of-memory killer kills (SIGKILL), the job fails naming the signal and what to do, the
API answers on and the dispatcher runs the next job."""

import os
import signal
import threading
import time

from service.dispatcher import Dispatcher
from service.jobs.process import ended_without_outcome
from tests.helpers import ON_SQLITE, api_client, attempt_processes, ready_scene, wait_for


def test_a_child_that_ends_without_an_outcome_is_named_by_its_signal_or_code():
    killed = ended_without_outcome(-signal.SIGKILL)
    assert "killed by SIGKILL" in killed and "out of memory" in killed
    assert "LECO_SLOT_MEMORY_MB" in killed
    assert "killed by SIGTERM" in ended_without_outcome(-signal.SIGTERM)
    assert "exited with code 3 without an outcome" in ended_without_outcome(3)


def child_of(job_id: int, timeout: float = 60) -> int:
    deadline = time.monotonic() + timeout
    while not (pids := attempt_processes(job_id, 1)):
        assert time.monotonic() < deadline, f"no child process runs job {job_id}"
        time.sleep(0.1)
    (pid,) = pids
    return pid


@ON_SQLITE
def test_a_killed_child_fails_its_job_and_the_api_and_dispatcher_go_on(service_settings):
    settings = service_settings.model_copy(update={"backend": "local"})
    with api_client(settings) as api:
        scene = ready_scene(api)
        body = {"scene": scene, "method": "switch", "profile": "smoke"}
        long = api.post("/v1/jobs", json={**body, "overrides": {"main_steps": 100_000}})
        assert long.status_code == 201, long.text
        dispatcher = Dispatcher(settings, poll_s=0.2)
        threading.Thread(target=dispatcher.run_forever, daemon=True).start()
        try:
            job_id = long.json()["id"]
            wait_for(api, job_id, lambda j: j["step"] >= 2, timeout=120)
            pid = child_of(job_id)
            assert pid != os.getpid()
            os.kill(pid, signal.SIGKILL)
            failed = wait_for(api, job_id, lambda j: j["state"] != "running", timeout=60)
            assert failed["state"] == "failed", failed
            assert failed["error"].startswith("the job's process was killed by SIGKILL")
            assert api.get("/healthz").status_code == 200
            short = api.post("/v1/jobs", json={**body, "overrides": {"main_steps": 4}})
            done = wait_for(api, short.json()["id"], lambda j: j["state"] != "queued")
            done = wait_for(api, done["id"], lambda j: j["state"] not in ("queued", "running"))
            assert done["state"] == "succeeded", done["error"]
            assert attempt_processes(job_id) == []
        finally:
            dispatcher.stop(wait=True)
