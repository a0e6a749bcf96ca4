"""The peg-in-hole user study of the paper, reproduced in simulation (`mmctl study`)."""
