"""The surfel map: fusing frames into it (``SurfelMapper``), rendering views of it, point clouds."""
