"""The fits a flower's normal comes from, in the order reports list them (a module of its
own, so the command line offers them without importing the fits)."""

#: Fitting methods: a plane, a superellipsoid and a paraboloid (the paper's three).
METHODS = ("plane", "superellipsoid", "paraboloid")
