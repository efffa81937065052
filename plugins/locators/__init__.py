"""Built-in locators: registration of merged frames (OpenCV, kornia, pycolmap)."""
