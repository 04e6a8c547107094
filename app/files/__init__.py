"""File reading (images, stacks, recordings) and the app's cache directory."""
