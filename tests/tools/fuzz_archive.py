"""Fuzzing of the `.symgs` reader: mutated archives must be refused cleanly or decode to finite scenes.

Seeds are archives of generated scenes written by every archive codec (float32, float16, quantised with the higher
SH per coefficient or as a palette), with and without mirror levels, plus any archives given with ``--archive``.
Each mutant comes from one seed and one mutation, drawn from ``(--seed, index)`` alone, so ``--replay INDEX``
rebuilds it. Mutations come in two families:

    raw   bytes changed where they lie (bit flips, overwritten spans, truncation, appended, inserted or deleted
          bytes): the checksums still describe the original, so nearly all must end at a CRC;
    crc   structure-aware, then re-framed with every checksum, offset and length recomputed, so each reaches the
          validation or decoder it targets: a header value replaced (scaled by powers of ten, negated, zeroed, made
          huge, tiny, of another type), a section payload's bytes changed, a payload's zstd frame decompressed,
          changed and recompressed, two sections' payloads swapped, or an archive that claims far more than it
          holds (hundreds of thousands of Gaussians in a few kilobytes of zeros, or level bits that expand them
          a hundredfold): refused before they are decoded, ``disproportionate``.

Every mutant is decoded (``decode_archive``), expanded through its levels and, when accepted, written in every
export format. Outcomes: ``refused`` (ArchiveError, counted by code; or ValueError from an export writer that
cannot hold the scene), ``accepted`` (a finite scene), ``non_finite`` (an accepted scene with a NaN or infinity,
stored or expanded), ``crash`` (any other exception, or a worker process that died) and ``hang`` (past
``--timeout`` seconds).

    .venv/bin/python tests/tools/fuzz_archive.py --mutants 100000 --workers 2
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
import zstandard  # noqa: E402

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
OUTCOMES = ("refused", "accepted", "non_finite", "crash", "hang")


# ---------------------------------------------------------------------------------------------------- seeds


def seeds_of(archives: tuple[str, ...], generated: bool = True) -> tuple[tuple[str, bytes], ...]:
    """The generated seeds (unless ``generated`` is false) and the archives at ``archives``."""
    given = tuple((Path(a).name, Path(a).read_bytes()) for a in archives)
    return (generated_seeds() if generated else ()) + given


@lru_cache(maxsize=1)
def generated_seeds() -> tuple[tuple[str, bytes], ...]:
    """(name, archive) of small generated scenes, one per archive codec, levels and SH degree."""
    from symgs_core.codec import ArchiveContents, QuantSteps, coding_order, encode_archive
    from symgs_core.mirror import Plane
    from symgs_core.synthetic import synthetic_scene

    palette = QuantSteps(sh_palette=32).archive_codec(2.0, "fuzz-palette")
    seeds = []
    for codec, degree, levels in [("lossless", 1, 2), ("float16", 2, 1), ("quantized", 0, 0), ("quantized", 3, 2),
                                  (palette, 2, 3)]:  # fmt: skip
        scene = synthetic_scene("global", n=120, seed=degree + levels, sh_degree=degree).scene
        g = torch.Generator().manual_seed(levels)
        planes = [Plane.from_tensor(torch.randn(3, generator=g, dtype=torch.float64), 0.1 * i) for i in range(levels)]
        bits = torch.rand(len(scene), levels, generator=g) < 0.3
        perm = coding_order(scene, bits)
        contents = ArchiveContents(scene.select(perm), planes, bits[perm], {"source": "fuzz"})
        name = codec if isinstance(codec, str) else codec.name
        seeds.append((f"{name}-sh{degree}-L{levels}", encode_archive(contents, codec=codec)))
    return tuple(seeds)


# ------------------------------------------------------------------------------------------- archive layout


def split(data: bytes) -> tuple[dict[str, Any], list[bytes]]:
    """The header object and each section's payload of a well-formed archive (a seed)."""
    from symgs_core.codec.container import PREFIX_SIZE

    length = int.from_bytes(data[12:16], "little")
    header = json.loads(zstandard.ZstdDecompressor().decompress(data[PREFIX_SIZE : PREFIX_SIZE + length]))
    body = data[PREFIX_SIZE + length :]
    return header, [body[s["offset"] : s["offset"] + s["length"]] for s in header["sections"]]


def join(header: dict[str, Any], payloads: list[bytes]) -> bytes:
    """An archive of ``header`` and ``payloads`` with offsets, lengths and every CRC recomputed; the header's
    other fields are written as they are (NaN and Infinity included, as a hostile writer would)."""
    import zlib

    from symgs_core.codec.container import FORMAT_VERSION, MAGIC

    offset, sections = 0, header.get("sections")
    for section, payload in zip(sections if isinstance(sections, list) else [], payloads, strict=False):
        if isinstance(section, dict):
            section.update(offset=offset, length=len(payload), crc32=zlib.crc32(payload))
        offset += len(payload)
    text = json.dumps(header, separators=(",", ":")).encode()
    packed = zstandard.ZstdCompressor(level=3).compress(text)
    prefix = MAGIC + FORMAT_VERSION.to_bytes(4, "little") + len(packed).to_bytes(4, "little")
    return prefix + zlib.crc32(packed).to_bytes(4, "little") + packed + b"".join(payloads)


# ------------------------------------------------------------------------------------------------- mutations


def _span(rng: np.random.Generator, size: int, most: int = 64) -> tuple[int, int]:
    start = int(rng.integers(0, max(size, 1)))
    return start, min(size, start + int(rng.integers(1, most + 1)))


def _bytes(rng: np.random.Generator, data: bytes) -> bytes:
    """One change to ``data`` where it lies."""
    data, kind = bytearray(data), int(rng.integers(0, 6))
    if kind == 0 and data:  # flip 1-8 bits
        for _ in range(int(rng.integers(1, 9))):
            data[int(rng.integers(0, len(data)))] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1 and data:  # overwrite a span with random bytes, or with one value
        start, end = _span(rng, len(data))
        fill = rng.integers(0, 256, end - start) if rng.random() < 0.5 else [int(rng.choice([0, 255]))] * (end - start)
        data[start:end] = bytes(int(v) for v in fill)
    elif kind == 2:  # truncate
        del data[int(rng.integers(0, len(data) + 1)) :]
    elif kind == 3:  # append
        data += rng.integers(0, 256, int(rng.integers(1, 64))).astype(np.uint8).tobytes()
    elif kind == 4:  # insert
        at = int(rng.integers(0, len(data) + 1))
        data[at:at] = rng.integers(0, 256, int(rng.integers(1, 16))).astype(np.uint8).tobytes()
    elif data:  # delete a span
        start, end = _span(rng, len(data), 16)
        del data[start:end]
    return bytes(data)


def _leaves(obj: Any, path: tuple = ()) -> Iterator[tuple]:
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(obj, list):
        yield path
        for i, v in enumerate(obj):
            yield from _leaves(v, (*path, i))
    else:
        yield path


def _hostile(rng: np.random.Generator, value: Any) -> Any:
    """A value in place of ``value``: mostly a number near or far from it, sometimes another type."""
    kind = int(rng.integers(0, 12))
    number = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else 1.0
    if kind < 4:
        scaled = number * 10.0 ** int(rng.integers(-300, 300))
        return int(scaled) if isinstance(value, int) and abs(scaled) < 2**70 else scaled
    if kind == 4:
        return -value if isinstance(value, (int, float)) and not isinstance(value, bool) else 0
    if kind == 5:
        return type(value)(0) if isinstance(value, (int, float)) and not isinstance(value, bool) else 0
    if kind == 6:
        return [float("nan"), float("inf"), -float("inf"), 1e-310, 5e-324, 3.4028235e38][int(rng.integers(0, 6))]
    if kind == 7:
        return int(rng.choice([-1, 1, 2**31, 2**32, 2**53 + 1, 2**63, 10**30]))
    if kind == 8 and isinstance(value, int) and not isinstance(value, bool):
        return value + int(rng.integers(-3, 4))
    if kind == 9:
        return [None, True, False, "", "x" * 70, [], {}][int(rng.integers(0, 7))]
    if kind == 10 and isinstance(value, list):
        return value[: int(rng.integers(0, len(value) + 1))] + value[: int(rng.integers(0, 3))]
    return [number] * int(rng.integers(0, 5))


def _set(obj: Any, path: tuple, value: Any) -> None:
    for key in path[:-1]:
        obj = obj[key]
    obj[path[-1]] = value


def _get(obj: Any, path: tuple) -> Any:
    for key in path:
        obj = obj[key]
    return obj


def mutate_header(rng: np.random.Generator, seed: bytes) -> bytes:
    header, payloads = split(seed)
    for _ in range(int(rng.integers(1, 3))):
        leaves = [p for p in _leaves(header) if p]
        if not leaves:
            break
        path = leaves[int(rng.integers(0, len(leaves)))]
        _set(header, path, _hostile(rng, _get(header, path)))
    return join(header, payloads)


def mutate_payload(rng: np.random.Generator, seed: bytes) -> bytes:
    header, payloads = split(seed)
    i = int(rng.integers(0, len(payloads)))
    payloads[i] = _bytes(rng, payloads[i])
    return join(header, payloads)


def mutate_inner(rng: np.random.Generator, seed: bytes) -> bytes:
    """A change inside a payload's zstd frame (or inside the first frame of a multi-part payload), recompressed."""
    header, payloads = split(seed)
    framed = [i for i, p in enumerate(payloads) if ZSTD_MAGIC in p[:8]]
    if not framed:
        return mutate_payload(rng, seed)
    i = framed[int(rng.integers(0, len(framed)))]
    at = payloads[i].index(ZSTD_MAGIC)
    reader = zstandard.ZstdDecompressor().decompressobj()
    raw = reader.decompress(payloads[i][at:])
    rest = reader.unused_data
    inner = zstandard.ZstdCompressor(level=1, write_content_size=True).compress(_bytes(rng, raw))
    prefix = payloads[i][:at]
    if at == 4:  # a join_parts stream: keep its length prefix true
        prefix = len(inner).to_bytes(4, "little")
    payloads[i] = prefix + inner + rest
    return join(header, payloads)


def mutate_swap(rng: np.random.Generator, seed: bytes) -> bytes:
    header, payloads = split(seed)
    i, j = (int(v) for v in rng.choice(len(payloads), 2, replace=False))
    payloads[i], payloads[j] = payloads[j], payloads[i]
    if rng.random() < 0.5:
        header["sections"][i], header["sections"][j] = header["sections"][j], header["sections"][i]
    return join(header, payloads)


def _zeros(size: int) -> bytes:
    """One zstd frame, declaring its size, of ``size`` zero bytes: a few dozen bytes a megabyte."""
    writer = zstandard.ZstdCompressor(level=1).compressobj(size=size)
    block = bytes(1 << 20)
    return b"".join(writer.compress(block[: min(len(block), size - at)]) for at in range(0, size, len(block))) + (
        writer.flush()
    )


def claiming(count: int, sh_degree: int, planes: list[dict[str, Any]], *, bits: bool = True) -> bytes:
    """A valid archive of ``count`` stored Gaussians whose every attribute is zero, with each level's bit set for all
    of them (``bits``) or none: a few kilobytes that claim millions of Gaussians, or billions once expanded."""
    from symgs_core.codec.classes import CLASSES
    from symgs_core.codec.masks import PACKED
    from symgs_core.scene import SH_REST_COUNT

    columns = {"means": 3, "quats": 4, "scales": 3, "opacities": 1, "sh_dc": 3, "sh_rest": 3 * SH_REST_COUNT[sh_degree]}
    sections, payloads = [], []
    for name, width in columns.items():
        payloads.append(_zeros(4 * count * width))
        sections.append({"name": name, "codec": "f32-zstd", "raw_length": 4 * count * width,
                         "params": {"layout": "rows"}})  # fmt: skip
    column = np.packbits(np.full(count, bits)).tobytes()
    raw = b"".join(bytes([PACKED]) + column for _ in planes)
    payloads.append(zstandard.ZstdCompressor(level=3).compress(raw))
    sections.append({"name": "bits", "codec": "mask-zstd", "raw_length": len(raw), "params": {}})
    classes = CLASSES.encode(np.zeros(count, np.uint8))
    payloads.append(classes.payload)
    sections.append({"name": "classes", "codec": CLASSES.name, "raw_length": count, "params": {}})
    from symgs_core.cameras import COORDINATE_CONVENTION

    header = {"count": count, "sh_degree": sh_degree, "coordinate_convention": COORDINATE_CONVENTION,
              "codec": "lossless", "planes": planes, "sections": sections, "meta": {}}  # fmt: skip
    return join(header, payloads)


def mutate_claim(rng: np.random.Generator, seed: bytes) -> bytes:
    """The seed's planes and SH degree in an archive that claims far more than it holds: hundreds of thousands of
    stored Gaussians in a few kilobytes, or a few tens of thousands whose level bits, all set, expand them a
    hundredfold."""
    header, _ = split(seed)
    planes = header["planes"] or [{"normal": [1.0, 0.0, 0.0], "offset": 0.0}]
    if rng.random() < 0.5:
        return claiming(int(rng.integers(200_000, 1_000_000)), header["sh_degree"], planes, bits=False)
    extra = [{"normal": [0.0, 1.0, 0.0], "offset": 0.1 * i} for i in range(int(rng.integers(7, 10)) - len(planes))]
    return claiming(int(rng.integers(20_000, 60_000)), header["sh_degree"], planes + extra)


MUTATORS: dict[str, tuple[str, Callable[[np.random.Generator, bytes], bytes]]] = {
    "bytes": ("raw", _bytes),
    "header": ("crc", mutate_header),
    "payload": ("crc", mutate_payload),
    "inner": ("crc", mutate_inner),
    "swap": ("crc", mutate_swap),
    "claim": ("crc", mutate_claim),
}
WEIGHTS = {"bytes": 0.3, "header": 0.3, "payload": 0.2, "inner": 0.13, "swap": 0.05, "claim": 0.02}


def mutant(index: int, seed: int, seeds: tuple[tuple[str, bytes], ...]) -> tuple[str, str, bytes]:
    """(seed name, mutator name, bytes) of mutant ``index``."""
    rng = np.random.default_rng([seed, index])
    name, data = seeds[int(rng.integers(0, len(seeds)))]
    names = list(WEIGHTS)
    which = names[int(rng.choice(len(names), p=[WEIGHTS[n] for n in names]))]
    for _ in range(10):  # a mutation can undo itself (the same bit flipped twice): draw again
        mutated = MUTATORS[which][1](rng, data)
        if mutated != data:
            break
    return name, which, mutated


# ---------------------------------------------------------------------------------------------------- running


class _Hang(Exception):
    pass


def _alarm(_signum: int, _frame: object) -> None:
    raise _Hang


def classify(data: bytes) -> tuple[str, str]:
    """(outcome, detail) of decoding ``data``: see the module docstring."""
    from symgs_core.codec import ArchiveError, decode_archive, expand_archive
    from symgs_core.export.formats import EXPORTS

    try:
        contents = decode_archive(data)
    except ArchiveError as exc:
        return "refused", exc.code
    scenes = (contents.stored, expand_archive(contents))
    for scene in scenes:
        for name, value in scene.tensors().items():
            if not torch.isfinite(value).all():
                return "non_finite", name
    for fmt in EXPORTS:
        try:
            fmt.write(scenes[1])
        except ValueError as exc:
            return "refused", f"export {fmt.name}: {str(exc)[:60]}"
    return "accepted", ""


@dataclass
class Tally:
    counts: Counter = field(default_factory=Counter)  # (family, outcome) -> mutants
    codes: Counter = field(default_factory=Counter)  # refusal code -> mutants
    examples: list[dict] = field(default_factory=list)  # crashes, hangs and non-finite decodes, to replay

    def add(self, other: Tally) -> None:
        self.counts.update(other.counts)
        self.codes.update(other.codes)
        self.examples.extend(other.examples)


def run_chunk(start: int, stop: int, seed: int, timeout: float, archives: tuple[str, ...], generated: bool) -> Tally:
    torch.set_num_threads(1)
    seeds = seeds_of(archives, generated)
    signal.signal(signal.SIGALRM, _alarm)
    tally = Tally()
    for index in range(start, stop):
        name, which, data = mutant(index, seed, seeds)
        family = MUTATORS[which][0]
        signal.setitimer(signal.ITIMER_REAL, timeout)
        try:
            outcome, detail = classify(data)
        except _Hang:
            outcome, detail = "hang", f"over {timeout} s"
        except Exception as exc:  # noqa: BLE001 - what the fuzzer is here to find
            outcome, detail = "crash", "".join(traceback.format_exception_only(exc)).strip()[:300]
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        tally.counts[(family, outcome)] += 1
        if outcome == "refused":
            tally.codes[detail.split(":")[0]] += 1
        elif outcome != "accepted":
            example = {"index": index, "seed": name, "mutator": which, "outcome": outcome, "detail": detail}
            tally.examples.append(example)
    return tally


def fuzz(mutants: int, *, seed: int = 0, workers: int = 1, timeout: float = 5.0, chunk: int = 500,
         archives: tuple[str, ...] = (), generated: bool = True) -> Tally:  # fmt: skip
    """Run ``mutants`` mutants in ``workers`` processes (in this process when 1)."""
    tally = Tally()
    spans = [(i, min(i + chunk, mutants)) for i in range(0, mutants, chunk)]
    if workers <= 1:
        for start, stop in spans:
            tally.add(run_chunk(start, stop, seed, timeout, archives, generated))
        return tally
    pending = spans
    while pending:
        again = []
        with ProcessPoolExecutor(workers) as pool:
            futures = [(pool.submit(run_chunk, start, stop, seed, timeout, archives, generated), (start, stop))
                       for start, stop in pending]  # fmt: skip
            for future, (start, stop) in futures:
                try:
                    tally.add(future.result())
                except BrokenProcessPool:  # a process died: run its mutants again one by one to find which
                    if stop - start > 1:
                        again += [(i, i + 1) for i in range(start, stop)]
                    else:
                        tally.counts[("?", "crash")] += 1
                        tally.examples.append({"index": start, "outcome": "crash", "detail": "the process died"})
        pending = again
    return tally


def report(tally: Tally, seconds: float) -> str:
    lines = ["| family | mutants | refused | accepted | non-finite | crash | hang |", "|---|" + "---:|" * 6]
    for family in ("raw", "crc"):
        row = [tally.counts[(family, o)] for o in OUTCOMES]
        lines.append(f"| {family} | {sum(row):,} | " + " | ".join(f"{v:,}" for v in row) + " |")
    total = [sum(tally.counts[(f, o)] for f in ("raw", "crc", "?")) for o in OUTCOMES]
    lines.append(f"| all | {sum(total):,} | " + " | ".join(f"{v:,}" for v in total) + " |")
    codes = ", ".join(f"{code} {n:,}" for code, n in tally.codes.most_common())
    lines += ["", f"Refusals by code: {codes}.", f"{sum(total):,} mutants in {seconds:.0f} s."]
    for example in tally.examples[:20]:
        lines.append(f"- {example}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mutants", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds before a decode counts as a hang")
    parser.add_argument("--archive", action="append", default=[], help="another seed archive (.symgs)")
    parser.add_argument("--only-archives", action="store_true", help="no generated seeds: the --archive ones only")
    parser.add_argument("--replay", type=int, help="decode mutant INDEX and print what happens")
    parser.add_argument("--json", type=Path, help="write the counts here")
    args = parser.parse_args()
    if args.replay is not None:
        seeds = seeds_of(tuple(args.archive), not args.only_archives)
        name, which, data = mutant(args.replay, args.seed, seeds)
        print(f"mutant {args.replay}: seed {name}, mutator {which}, {len(data)} bytes")
        print(classify(data))
        return
    started = time.perf_counter()
    tally = fuzz(args.mutants, seed=args.seed, workers=args.workers, timeout=args.timeout,
                 archives=tuple(args.archive), generated=not args.only_archives)  # fmt: skip
    seconds = time.perf_counter() - started
    print(report(tally, seconds))
    if args.json is not None:
        counts = {f"{family}/{outcome}": n for (family, outcome), n in tally.counts.items()}
        args.json.write_text(json.dumps({"counts": counts, "codes": dict(tally.codes), "examples": tally.examples,
                                         "seconds": seconds}, indent=1))  # fmt: skip
    bad = sum(n for (_, outcome), n in tally.counts.items() if outcome in ("crash", "hang", "non_finite"))
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
