"""The objectives' default term weights, in a module that imports no torch: the command line shows
them in ``--help`` without loading the fitting code."""

# The normal-map objective's silhouette term, against its normal term.
SILHOUETTE_WEIGHT = 1.0
# The photographs' objective: the mask term (rendered opacity against the views' masks) and the SSIM
# term, against the colour term.
MASK_WEIGHT = 0.1
SSIM_WEIGHT = 0.2
