"""Image processing on AFM height maps: drift, tip, landmarks, user image files."""
