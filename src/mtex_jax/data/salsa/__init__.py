"""The CMU salsa clips (see CREDIT.txt)."""
