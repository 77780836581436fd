"""macsplat's benchmarks: each module a script that prints Markdown tables, run from the repository root as
``python -m benchmarks.<name> [options]`` (``--help`` lists them).

What each measures, its command and today's figure: ``benchmarks/README.md``; the dated measurements behind the
figures: ``benchmarks/history/<topic>.md``. Shared helpers: :mod:`._common` (tables, timing through the engine's
``on_stage`` callback, peak memory, JSON) and :mod:`._dev` (the development scenes through
:mod:`macsplat_cli.datasets`).
"""
