"""Estimation: fitting plant and effect parameters to recordings, the lab's classic methods, and the
diagnosis of what physics a recording shows that the model leaves out."""
