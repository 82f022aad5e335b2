"""Where simulator and policies meet: Tables 1 and 2, the controller bench and Fig. 4."""
