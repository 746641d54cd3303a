"""Pure core: numpy arrays and frozen configs in, results out. No Zenoh, no files, no printing."""
