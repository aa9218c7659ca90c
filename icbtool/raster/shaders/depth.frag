// Depth-only pass: no colour output.
void main() {}
