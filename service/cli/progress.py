"""Rich progress bars that follow jobs over the API (``symgs submit``, ``symgs demo``)."""

from __future__ import annotations

import threading

from rich.console import Console, Group
from rich.progress import BarColumn, Progress, TaskID, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from api_schemas import Job, JobEvent
from symgs_core.progress import format_seconds

from ..client import SymgsClient


def job_progress(console: Console) -> Progress:
    return Progress(
        TextColumn("[bold]{task.fields[label]}", justify="left"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[left]}"),
        console=console,
    )


def _left(event: JobEvent) -> str:
    """The worker's estimate of the time left, while the job runs."""
    if event.state != "running":
        return ""
    return f"left {format_seconds(event.eta_s)}"


def _status(event: JobEvent) -> str:
    if event.kind == "state":
        return event.state
    level = f" L{event.level}" if event.level is not None else ""
    return f"{event.stage}{level}: {event.message}"[:60]


def follow(client: SymgsClient, jobs: dict[str, str], console: Console) -> dict[str, Job]:
    """Follow jobs (id -> label) with one bar each until all finish; returns the final jobs by id."""
    finals: dict[str, Job] = {}
    errors: list[BaseException] = []
    with job_progress(console) as progress:
        tasks = {
            job_id: progress.add_task("", total=1.0, label=label, status="queued", left="")
            for job_id, label in jobs.items()
        }

        def run(job_id: str, task: TaskID) -> None:
            def update(event: JobEvent) -> None:
                progress.update(task, completed=event.progress, status=_status(event), left=_left(event))

            try:
                finals[job_id] = client.wait(job_id, on_event=update)
            except Exception as exc:  # reported after the bars end
                errors.append(exc)

        threads = [threading.Thread(target=run, args=item, daemon=True) for item in tasks.items()]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    if errors:
        raise errors[0]
    return finals


def jobs_table(jobs: list[tuple[str, Job]]) -> Group:
    """The jobs' headline figures, then each job's notes (what would make its result better)."""
    table = Table(title="jobs")
    for column in ("scene", "id", "state", "input", "output", "ratio", "vs baseline", "PSNR dB", "mirrors"):
        table.add_column(column)
    for label, job in jobs:
        m = job.metrics
        if m is None:
            why = f"{job.error.code}: {job.error.message}" if job.error else ""
            table.add_row(label, job.id, job.state, why[:60], "", "", "", "", "")
            continue
        psnr = f"{m.psnr:.2f}" if m.psnr is not None else "inf"
        table.add_row(
            label, job.id, job.state, f"{m.input_bytes:,} B", f"{m.output_bytes:,} B", f"{m.ratio_to_ply:.1f}x",
            f"{m.ratio_to_baseline:.2f}x", psnr, str(len(job.mirrors)),
        )  # fmt: skip
    notes = [Text(f"{label}: {note}") for label, job in jobs if job.metrics for note in job.metrics.notes]
    return Group(table, *notes)
