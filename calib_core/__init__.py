"""The mathematics of lasercal: pure numpy/scipy, no I/O beyond parsing, no UI."""
