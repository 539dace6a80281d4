"""From sensor streams to landmark visits (thesis Ch. 3.10, 4): laser patches and registration, laser
odometry, Bayesian surprise, the landmark detectors and the streaming visit extractor."""
