"""The embedded synthetic RGB-D sequence: scene, camera path and renderer."""
