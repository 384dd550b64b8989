"""Benchmarks: code, not timed tests. Each module writes its table with the command behind it."""
