// Placeholder demo, replaced by the real pipeline demo.
#include <cstdio>
#include "epona/core/tensor.hpp"
int main() { std::puts("epona demo"); return 0; }
