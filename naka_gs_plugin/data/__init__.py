"""Low-light scene I/O: the ``lowlight-data`` dataparser and the enhancing datamanager."""
