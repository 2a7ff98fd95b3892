#include <cstdio>
int main() { std::puts("mocap: not built yet"); return 1; }
