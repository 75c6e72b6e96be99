"""Natural images (and, later, footage) for augmentations and distracting scenes."""
from imssr.data.images import IMAGE_DIR_ENV, builtin_photographs, image_pool, load_image_folder

__all__ = ["IMAGE_DIR_ENV", "builtin_photographs", "image_pool", "load_image_folder"]
