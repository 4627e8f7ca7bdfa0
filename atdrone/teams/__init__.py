"""Teams: learners and partners in the pursuer slots, the adaptive-teaming view, evaluation and reports."""
