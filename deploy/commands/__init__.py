"""One module per `cadsplat` sub-command; imported only when that command runs."""
