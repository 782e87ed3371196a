"""The test suite and its helpers, a package so that the benchmarks (``python -m tests.bench.NAME``) and the soak runs
(``python -m tests.soak.NAME``) import the helpers as ``tests.fixtures``, ... from the repository root."""
