"""The thesis's chapter-2 models: TCSPC process, signal, noise, atmosphere, performance.

SI units inside (seconds, metres, watts, pascals, kelvin), units in names. Every function
is vectorised: array arguments broadcast.
"""
