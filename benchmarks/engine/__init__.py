"""The engine's benchmarks: ``python -m benchmarks.engine NAME`` (render, table1, capture, track, robustness, autoinit,
partial, clinical, models, hemodynamics). They import the engine only (``tests/test_import_graph.py``), so they run
where only the engine's packages are installed (a GPU box), from the repository root."""
