"""Virtual nano-hand executor: push actions with feedback and cancel."""
