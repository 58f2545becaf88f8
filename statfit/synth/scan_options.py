"""What a simulated scan can be asked for, in a module that imports neither trimesh nor SciPy: the
command line checks and shows these choices without loading the scanner."""

# Length units a scan may come in, as multiples of a metre.
UNITS_PER_METRE = {"m": 1.0, "cm": 100.0, "mm": 1000.0}
# What clutter a realistic scan can hold: hair over the scalp, a neck and shoulders tube below.
CLUTTER_PARTS = ("hair", "neck")
