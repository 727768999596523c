"""One module per workflow stage: read the stage's inputs, call the physics, write outputs.

The Snakemake scripts in ``workflow/scripts`` call exactly one function from here.
"""
