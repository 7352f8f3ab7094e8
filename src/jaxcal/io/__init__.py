"""Input and output at the edges: HDF5 contract files, importers of real recordings, serial devices."""
