"""NumPy/SciPy reference implementation of every op: the readable version of the math."""
