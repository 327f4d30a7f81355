"""rlmflow's side of HyperQueue: a local cluster, and one task per action.

The client blocks the whole process while it waits for a job (another thread's call hangs until
the wait ends), so nothing here blocks: `status` asks for a job's state and returns at once. The
engine makes one call at a time.
"""

from hyperqueue import Client, Job
from hyperqueue.cluster import LocalCluster, WorkerConfig
from hyperqueue.ffi.protocol import ResourceRequest
from hyperqueue.output import StdioDef


def start_cluster(server_dir, workers, cores):
    """A server and `workers` workers of `cores` cores each, in this process."""
    cluster = LocalCluster(server_dir=server_dir)
    for _ in range(workers):
        cluster.start_worker(WorkerConfig(cores=cores))
    return cluster


def server_dir(cluster):
    return cluster.cluster.server_dir


def stop_cluster(cluster):
    cluster.stop()


def connect(directory):
    """A client of the server in `directory`; raises if none answers."""
    return Client(directory)


def submit(client, name, args, cwd, stdout, stderr, cpus, gpus, stdin=None):
    """Submits one task running `args`; returns the job id.

    With `stdin` (a task with a store of its own), `stdout` and `stderr` are paths on the worker,
    kept there only if the task fails."""
    # A share of a GPU (0.25) or whole ones (1), as HyperQueue's fractional resources take them.
    resources = {"gpus/nvidia": int(gpus) if gpus == int(gpus) else gpus} if gpus else None
    if stdin is not None:
        stdout, stderr = StdioDef.remove_if_finished(stdout), StdioDef.remove_if_finished(stderr)
    job = Job(name=name, max_fails=1)
    job.program(
        args,
        cwd=cwd,
        stdout=stdout,
        stderr=stderr,
        stdin=stdin,
        name=name,
        resources=ResourceRequest(cpus=cpus, resources=resources),
        crash_limit=1,
    )
    return client.submit(job).id


class _Looked(Exception):
    pass


def status(client, job_id):
    """None while the job runs; then "" if it finished, else HyperQueue's reason it failed.

    The wait's progress callback hears the job's state first thing; raising there ends the
    wait at once."""
    seen = {}

    def look(jobs):
        seen.update(jobs)
        raise _Looked()

    try:
        failed = client.connection.wait_for_jobs([job_id], look)
    except _Looked:
        state = seen[job_id]
        if not state["completed"]:
            return None
        failed = [job_id] if state["failed"] else []
    if not failed:
        return ""
    tasks = client.connection.get_failed_tasks([job_id]).get(job_id, {})
    return "; ".join(t.error for t in tasks.values()) or "the task failed"
