"""mjx_morph: universal morphology control for UNIMAL robots in MuJoCo-MJX and JAX."""
__version__ = "0.1.0"
