"""Built-in compositors: the panorama from every binary frame and its homography."""
