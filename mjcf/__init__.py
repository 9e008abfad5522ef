"""The packaged MJCF models (installed as ``jaxsync.mjcf``)."""
