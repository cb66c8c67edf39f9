"""Benchmarks behind ``burrforce bench …``. Each writes its results to files in the repository
(``benchmarks/`` by default), never asserting speed inside unit tests."""
