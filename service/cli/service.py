"""`symgs serve | worker | submit | status | fetch | demo`: run the service and use it over HTTP."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from collections import defaultdict
from itertools import combinations
from pathlib import Path

DEFAULT_SERVER = "http://127.0.0.1:8000"
_OWN_FILES = 32  # descriptors the API keeps besides its clients' connections: Redis, storage, logs, libraries


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the HTTP API (uvicorn)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (0.0.0.0 for all)")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=1, help="API processes")
    p.set_defaults(func=serve)

    p = sub.add_parser("worker", help="run a Celery worker for the gpu or cpu queue")
    p.add_argument("--mode", choices=("gpu", "cpu"), required=True)
    p.add_argument("--concurrency", type=int, default=1, help="jobs at once (cpu mode only; gpu runs one)")
    p.add_argument("--loglevel", default="INFO")
    p.set_defaults(func=worker)

    def client_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--server", default=os.environ.get("SYMGS_SERVER", DEFAULT_SERVER), help="API base URL")
        p.add_argument("--api-key", default=os.environ.get("SYMGS_API_KEY"), help="Bearer key (or SYMGS_API_KEY)")

    p = sub.add_parser("submit", help="upload scenes for compression and follow their progress")
    p.add_argument("scenes", nargs="+", type=Path, metavar="SCENE.ply")
    p.add_argument("--images", type=Path, help="dataset folder (NeRF-Synthetic or COLMAP) of the one scene")
    p.add_argument("--params", help="job parameters as JSON, or @file.json")
    p.add_argument("--no-wait", action="store_true", help="print the job ids and return")
    p.add_argument(
        "-o", "--output", type=Path,
        help="download each finished job's results into OUTPUT/<scene>/, <scene> being the file name without its "
        "suffix; scenes that share it keep the path that tells them apart (a/scene.ply b/scene.ply: OUTPUT/a/scene/ "
        "and OUTPUT/b/scene/)",
    )  # fmt: skip
    client_options(p)
    p.set_defaults(func=submit)

    p = sub.add_parser("status", help="show a job")
    p.add_argument("job_id")
    p.add_argument("--json", action="store_true", help="print the job as JSON")
    client_options(p)
    p.set_defaults(func=status)

    p = sub.add_parser("fetch", help="download a finished job's results")
    p.add_argument("job_id")
    p.add_argument("-o", "--output", type=Path, required=True, help="folder to write into")
    client_options(p)
    p.set_defaults(func=fetch)

    p = sub.add_parser("demo", help="run the whole service locally on a generated symmetric scene")
    p.add_argument("-o", "--output", type=Path, default=Path("symgs-demo"), help="folder for the results")
    p.add_argument("--gaussians", type=int, default=4000)
    p.set_defaults(func=demo)


def serve(args: argparse.Namespace) -> int:
    import uvicorn
    from pydantic import ValidationError

    from .parser import CliError

    try:  # the gateway builds the Celery app from the settings as it is read: a bad setting raises there already
        from worker.gateway import Settings

        from ..api.auth import refusal

        settings = Settings()
    except ValidationError as exc:
        raise CliError("; ".join(e["msg"].removeprefix("Value error, ") for e in exc.errors())) from None
    why = refusal(settings)
    if why is not None:
        raise CliError(why)
    descriptors = _raise_open_files_limit()
    uvicorn.run(
        "service.api.app:create_app", factory=True, host=args.host, port=args.port, workers=args.workers,
        http="service.api.connections:GuardedH11Protocol",  # deadlines for heads and bodies, a bound on waiting
        backlog=_backlog(descriptors, settings.max_pending_connections),
    )  # fmt: skip
    return 0


def _raise_open_files_limit() -> int:
    """Every connection holds a descriptor: take the most the system allows this process, not the soft limit (often
    1,024), which a few hundred clients and the API's own files reach. Returns the limit now in force."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = min(hard, 1 << 20) if hard != resource.RLIM_INFINITY else 1 << 20
    if soft < target:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    return max(soft, target)


def _backlog(descriptors: int, max_pending: int) -> int:
    """The listen backlog, which is also how many connections asyncio accepts at once before any of them is seen
    (and those past ``max_pending`` closed): a burst of uvicorn's 2,048 exhausts the descriptors of a 1,024-descriptor
    process, and on "Too many open files" asyncio stops accepting for a second at a time while a flood refills the
    queue. asyncio accepts a burst in one turn of its loop, makes the connections' protocols in the next and connects
    them in the one after, so three bursts may be open before the first one's extra connections are closed: each takes
    at most a third of the descriptors left beside the connections waiting for their head and the process's own."""
    return min(2048, max(16, (descriptors - max_pending - _OWN_FILES) // 3))


def worker(args: argparse.Namespace) -> int:
    from worker.gateway import run_worker

    from .parser import CliError

    try:
        run_worker(args.mode, concurrency=args.concurrency, loglevel=args.loglevel)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    return 0


def _params(text: str | None) -> dict | None:
    from .parser import CliError

    if text is None:
        return None
    try:
        raw = Path(text[1:]).read_text() if text.startswith("@") else text
        value = json.loads(raw)
    except (OSError, ValueError) as exc:
        raise CliError(f"--params: {exc}") from None
    if not isinstance(value, dict):
        raise CliError("--params must be a JSON object")
    return value


def _client(args: argparse.Namespace):  # noqa: ANN202 - SymgsClient, imported lazily
    from ..client import SymgsClient

    return SymgsClient(args.server, args.api_key)


def _api_errors(fn):  # noqa: ANN001, ANN202 - turns client errors into CLI errors
    def wrapped(args: argparse.Namespace) -> int:
        import httpx

        from ..client import ApiClientError, UnsafeArtifactName
        from .parser import CliError

        try:
            return fn(args)
        except (ApiClientError, UnsafeArtifactName) as exc:
            raise CliError(str(exc)) from None
        except httpx.TransportError as exc:
            raise CliError(f"cannot reach {args.server}: {exc}") from None

    return wrapped


def _labels(scenes: list[Path]) -> list[str]:
    """Each scene's name on its progress bar and, without its suffix, its results folder: the file name, or where
    scenes share a stem (every 3DGS training run writes point_cloud.ply), the path from the folder holding them all."""
    paths = [Path(os.path.abspath(scene)) for scene in scenes]
    by_stem: defaultdict[str, list[Path]] = defaultdict(list)
    for path in paths:
        by_stem[path.stem.casefold()].append(path)  # casefolded: Scene/ and scene/ are one folder on some disks
    labels = []
    for path in paths:
        same = by_stem[path.stem.casefold()]
        top = Path(os.path.commonpath([other.parent for other in same])) if len(same) > 1 else path.parent
        labels.append(path.relative_to(top).as_posix())
    return labels


def _result_folders(scenes: list[Path], labels: list[str], output: Path) -> list[Path]:
    """Each scene's folder under ``output``; refused where two would mix (a scene given twice, scene.ply beside
    scene.PLY, or one folder inside another), before anything is submitted."""
    from .parser import CliError

    folders = [Path(label).with_suffix("") for label in labels]
    keys = [tuple(part.casefold() for part in folder.parts) for folder in folders]
    for i, j in combinations(range(len(scenes)), 2):
        outer, inner = sorted((i, j), key=lambda k: len(keys[k]))
        if keys[inner][: len(keys[outer])] == keys[outer]:
            raise CliError(
                f"-o: {scenes[i]} and {scenes[j]} would mix their results in {output / folders[outer]}; submit them "
                "with separate -o folders"
            )
    return [output / folder for folder in folders]


def _download(client, job_id: str, folder: Path) -> list[Path]:  # noqa: ANN001 - SymgsClient, imported lazily
    from .parser import cannot_write

    try:
        return client.fetch(job_id, folder)
    except OSError as exc:  # a full disk, a folder that cannot be made: named, not a traceback
        raise cannot_write("-o", folder, exc) from None


@_api_errors
def submit(args: argparse.Namespace) -> int:
    from rich.console import Console

    from ..client import zip_folder
    from .parser import CliError, check_output
    from .progress import follow, jobs_table

    if args.images is not None and len(args.scenes) != 1:
        raise CliError("--images belongs to one scene; submit scenes with datasets one at a time")
    if args.images is not None and not args.images.is_dir():
        raise CliError(f"--images {args.images} is not a folder")
    for scene in args.scenes:
        if not scene.is_file():
            raise CliError(f"{scene} is not a file")
    check_output("-o", args.output, folder=True)
    labels = _labels(args.scenes)
    folders = _result_folders(args.scenes, labels, args.output) if args.output is not None else []
    params = _params(args.params)
    console = Console()
    with _client(args) as client, tempfile.TemporaryDirectory() as tmp:
        archive = None
        if args.images is not None:
            try:
                archive = zip_folder(args.images, Path(tmp) / f"{args.images.name}.zip")
            except (OSError, ValueError) as exc:  # an unreadable photograph, a date zip cannot store
                raise CliError(f"--images {args.images}: {exc}") from None
        jobs = {}
        for scene, label in zip(args.scenes, labels, strict=True):
            job = client.submit(scene, images=archive, params=params)
            jobs[job.id] = label
            console.print(f"{scene}: job {job.id} ({job.queue} queue)")
        if args.no_wait:
            return 0
        finals = follow(client, jobs, console)
        console.print(jobs_table([(jobs[i], finals[i]) for i in jobs]))
        for job_id, job in finals.items():
            if job.error is not None:  # in full: the table cuts long messages
                console.print(f"{jobs[job_id]}: {job.state}: {job.error.code}: {job.error.message}", soft_wrap=True)
        if args.output is not None:
            for job_id, folder in zip(jobs, folders, strict=True):
                if finals[job_id].state == "succeeded":
                    _download(client, job_id, folder)
            console.print(f"results in {args.output}/")
    return 0 if all(job.state == "succeeded" for job in finals.values()) else 1


@_api_errors
def status(args: argparse.Namespace) -> int:
    from rich.console import Console

    from .progress import jobs_table

    with _client(args) as client:
        job = client.job(args.job_id)
    if args.json:
        print(job.model_dump_json(indent=2))
        return 0
    console = Console()
    console.print(f"{job.id}: {job.state}, stage {job.stage}, {job.progress:.0%} {job.message}")
    if job.metrics is not None or job.error is not None:
        console.print(jobs_table([(job.scene.filename, job)]))
    if job.error is not None:  # in full: the table cuts long messages
        console.print(f"{job.scene.filename}: {job.state}: {job.error.code}: {job.error.message}", soft_wrap=True)
    return 0


@_api_errors
def fetch(args: argparse.Namespace) -> int:
    from .parser import CliError, check_output

    check_output("-o", args.output, folder=True)
    with _client(args) as client:
        job = client.job(args.job_id)
        if job.state != "succeeded":
            why = f" ({job.error.code}: {job.error.message})" if job.error is not None else ""
            raise CliError(f"job {job.id} is {job.state}{why}; only succeeded jobs have results")
        for path in _download(client, args.job_id, args.output):
            print(path)
    return 0


def demo(args: argparse.Namespace) -> int:
    from .demo import run_demo
    from .parser import check_output

    check_output("-o", args.output, folder=True)
    return run_demo(args.output, gaussians=args.gaussians)
