"""Data on disk: OpenEXR files, dataset folders, torch Datasets."""
