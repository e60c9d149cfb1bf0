"""Reading and writing fieldcal's files: stack folders, frame images, atomic writes (and, per document, its schema)."""
