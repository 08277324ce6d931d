// Sets the first `count` 32-bit words of the buffer bound at CLEAR_BINDING to `value` (GlContext.clear_words):
// the clear runs on the GPU, where moderngl's Buffer.clear maps the buffer and writes it from the CPU.
layout(std430, binding = CLEAR_BINDING) writeonly buffer Words { uint words_[]; };

uniform uint count;
uniform uint value;

void main() {
    uint i = invocation();
    if (i < count) words_[i] = value;
}
