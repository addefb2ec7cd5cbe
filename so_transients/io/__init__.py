"""Reading and writing simulated TOD, and the sotodlib obs loader for them."""
