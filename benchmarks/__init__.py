"""icbtool's benchmarks: each module is a script run as ``python -m benchmarks.NAME --out DIR``.

They are not tests (nothing here asserts a time). Each writes its numbers (JSON), plots, the
resolved settings, library versions, the machine and its load to ``--out``;
``python -m benchmarks.page`` turns the committed results in ``benchmarks/results/`` into
docs/benchmarks.md, where every table names the module that owns it.
"""
