"""Natural images and footage for augmentations and distracting scenes."""
from imssr.data.footage import FOOTAGE_DIR_ENV, builtin_footage, footage_pool, load_footage
from imssr.data.images import IMAGE_DIR_ENV, builtin_photographs, image_pool, load_image_folder

__all__ = ["FOOTAGE_DIR_ENV", "IMAGE_DIR_ENV", "builtin_footage", "builtin_photographs", "footage_pool",
           "image_pool", "load_footage", "load_image_folder"]
