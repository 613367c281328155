"""Test twins and test helpers, apart from the product: in-memory stand-ins for the store,
the event source and the publisher (held to the same contract suites as the adapters they
stand in for: tests/mapservice/adapters/test_*_contract.py), and the browser the UI tests
and the UI benchmark drive. Only tests and the benchmarks import this package (pyproject's
import contracts)."""
