"""One router per resource; ``app.py`` combines them."""
