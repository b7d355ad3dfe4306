"""What every network of the toolkit shares: the labelled-image format ("earcore-images",
`earcore.learning.shards`), its PNG codec (`earcore.learning.png`) and the torch dataset
over it (`earcore.learning.dataset`).

This area needs only numpy (and torch for the dataset): it never imports the compiled
core, so training runs from the source tree on a machine with Python, numpy and torch.
Nothing is imported here; import the modules themselves.
"""
