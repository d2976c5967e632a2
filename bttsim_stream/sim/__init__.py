"""Run-up simulation: speed profile, exact modal response, blade times of arrival and truth."""
