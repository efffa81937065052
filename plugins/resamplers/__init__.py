"""Built-in resamplers: which binary frames form each virtual exposure."""
