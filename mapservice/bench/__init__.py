"""Benchmarks and the bulk history loader (`mapservice bench ...`, `mapservice load-history`).
They measure the product from outside; the product never imports them (an import-contract
test checks it). Results go to BENCHMARKS.md.
"""
