"""A short run of the archive fuzzer (``tests/tools/fuzz_archive.py``; BENCHMARKS.md has the long one): every
mutant, raw or re-framed with valid checksums, is refused cleanly or decodes to a finite scene."""

from __future__ import annotations

from tests.tools.fuzz_archive import classify, fuzz, generated_seeds, mutant


def test_mutants_are_refused_or_finite() -> None:
    tally = fuzz(1500, seed=19, workers=1, timeout=10.0)
    bad = {key: n for key, n in tally.counts.items() if key[1] in ("crash", "hang", "non_finite")}
    assert bad == {}, tally.examples[:5]
    for family in ("raw", "crc"):
        assert tally.counts[(family, "refused")] > 100, tally.counts
    assert tally.counts[("crc", "accepted")] > 0  # harmless changes (meta, codec name) still decode
    assert {"bad_checksum", "bad_header", "corrupt_section", "truncated", "disproportionate"} <= set(tally.codes)


def test_mutants_replay_and_seeds_decode() -> None:
    seeds = generated_seeds()
    assert all(classify(data) == ("accepted", "") for _, data in seeds)
    assert mutant(123, 19, seeds) == mutant(123, 19, seeds)
    assert classify(seeds[0][1][:-1]) == ("refused", "truncated")
