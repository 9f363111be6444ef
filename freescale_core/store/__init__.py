"""The store: atomic files, Store, the published layout, pictures."""
