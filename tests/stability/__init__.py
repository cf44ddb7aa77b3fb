"""The numerical-stability suite (DESIGN.md "Numerical stability"); see ``cases.py``."""
