"""Data: the dataset type every scene loads into, the NeRF2 folder format, scenes, neighbor selection and the
datamodule that joins them into batches."""
