"""Implementation of jaxpso; the public modules re-export from here."""
