// The trust passes' shared declarations: the level size and OpenCV's BORDER_REFLECT index (...cba|abc...).
uniform ivec2 size;  // H, W of frame n

// BORDER_REFLECT (edge pixel repeated) of index i on an axis of n >= 1 pixels
int reflect_index(int i, int n) {
    if (n == 1) return 0;
    while (i < 0 || i >= n) i = i < 0 ? -i - 1 : 2 * n - i - 1;
    return i;
}
