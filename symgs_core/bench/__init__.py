"""Benchmarks against the peers' formats: ``suite.run_bench`` is what ``symgs bench`` runs.

Modules: ``suite`` (a bench over scenes: ``bench.json``, Markdown tables, charts), ``run`` (one scene's rows),
``peers`` and ``splat_transform`` (the other formats and the tool that writes them), ``half_ply`` (the float16 PLY
peer), ``curve`` (our rate-distortion curve and sizes at equal PSNR), ``rows`` (what every field means),
``tables``, ``charts`` (rate-distortion and speed-accuracy pictures), ``stamp`` (commit, machine and tool
versions under every figure).
"""
