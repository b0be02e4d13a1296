"""Speed benchmarks of ee-formation-env: ``python -m benchmarks.run`` (see ``docs/performance.md``)."""
