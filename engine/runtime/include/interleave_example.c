/*
 * interleave_example.c - a minimal C client of `interleave serve` (POSIX), using interleave_protocol.h.
 *
 *   cc -std=c11 -Wall -O2 -I engine/runtime/include engine/runtime/include/interleave_example.c -o il_example -lrt -lm
 *   interleave serve --listen unix:/tmp/interleave.sock &
 *   ./il_example /tmp/interleave.sock
 *
 * Opens an OpenCV-convention session (64x48 RGBA float, planar depth) with a half-resolution motion-vector
 * plane (protocol version 3: the segment is an anonymous memfd whose descriptor arrives with the HELLO
 * reply as SCM_RIGHTS ancillary data; a layout with a name is opened with shm_open instead), submits two frames of a fronto-parallel wall 2 m away while the camera moves
 * 1 cm to the right per frame (the second with its motion vectors), predicts the frame of the next step
 * and prints what came back. tests/runtime/test_server.py compiles and runs it. Error handling is minimal:
 * any failure exits with 1.
 */
#define _POSIX_C_SOURCE 200809L
#define _DEFAULT_SOURCE /* CMSG_SPACE */
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include "interleave_protocol.h"

enum { WIDTH = 64, HEIGHT = 48, CHANNELS = 4, MV_WIDTH = 32, MV_HEIGHT = 24 };

static int sock_fd = -1;
static int passed_fd = -1; /* a descriptor that came with the last reply (SCM_RIGHTS), or -1 */
static uint32_t next_id = 1;

static void die(const char *what) {
    fprintf(stderr, "il_example: %s\n", what);
    exit(1);
}

static void write_all(const void *data, size_t size) {
    const char *p = data;
    while (size > 0) {
        ssize_t n = write(sock_fd, p, size);
        if (n <= 0) die("write failed");
        p += n;
        size -= (size_t)n;
    }
}

/* Reads with recvmsg, so that a descriptor the server passes (with a reply carrying an il_layout) is kept. */
static void read_all(void *data, size_t size) {
    char *p = data;
    while (size > 0) {
        union { struct cmsghdr align; char buf[CMSG_SPACE(sizeof(int))]; } control;
        struct iovec iov = {p, size};
        struct msghdr msg = {0};
        msg.msg_iov = &iov;
        msg.msg_iovlen = 1;
        msg.msg_control = control.buf;
        msg.msg_controllen = sizeof control.buf;
        ssize_t n = recvmsg(sock_fd, &msg, 0);
        if (n <= 0) die("connection closed");
        for (struct cmsghdr *c = CMSG_FIRSTHDR(&msg); c != NULL; c = CMSG_NXTHDR(&msg, c)) {
            if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SCM_RIGHTS) memcpy(&passed_fd, CMSG_DATA(c), sizeof(int));
        }
        p += n;
        size -= (size_t)n;
    }
}

/* Sends one request and reads its reply payload into reply (reply_size bytes expected). */
static void request(uint16_t type, const void *payload, uint64_t size, void *reply, uint64_t reply_size) {
    il_header h = {IL_MAGIC, IL_VERSION, type, next_id++, 0, size};
    write_all(&h, sizeof h);
    if (size) write_all(payload, size);
    il_header r;
    read_all(&r, sizeof r);
    if (r.magic != IL_MAGIC || r.request_id != h.request_id || r.type != (type | IL_MSG_REPLY)) die("bad reply header");
    if (r.status != IL_OK) {
        char text[4097] = {0};
        read_all(text, r.payload_size < 4096 ? r.payload_size : 4096);
        fprintf(stderr, "il_example: server error %u: %s\n", r.status, text);
        exit(1);
    }
    if (r.payload_size != reply_size) die("unexpected reply size");
    if (reply_size) read_all(reply, reply_size);
}

static void set_pose(il_frame *f, double tx) {
    /* OpenCV: view = world_to_camera (camera at x = tx), projection = K in the top-left 3x3 */
    memset(f->view, 0, sizeof f->view);
    memset(f->projection, 0, sizeof f->projection);
    f->view[0] = f->view[5] = f->view[10] = f->view[15] = 1.0;
    f->view[3] = -tx;
    f->projection[0] = 50.0; f->projection[2] = WIDTH / 2.0;
    f->projection[5] = 50.0; f->projection[6] = HEIGHT / 2.0;
    f->projection[10] = 1.0;
}

int main(int argc, char **argv) {
    if (argc != 2) die("usage: il_example SOCKET_PATH");
    struct sockaddr_un addr = {0};
    addr.sun_family = AF_UNIX;
    strncpy(addr.sun_path, argv[1], sizeof addr.sun_path - 1);
    sock_fd = socket(AF_UNIX, SOCK_STREAM, 0);
    if (sock_fd < 0 || connect(sock_fd, (struct sockaddr *)&addr, sizeof addr) != 0) die("cannot connect");

    il_hello_with_motion hello = {0};
    hello.hello.engine = IL_ENGINE_OPENCV;
    hello.hello.depth_convention = IL_DEPTH_LINEAR;
    hello.hello.color_in = hello.hello.color_out = IL_COLOR_LINEAR;
    hello.hello.width = WIDTH;
    hello.hello.height = HEIGHT;
    hello.hello.channels = CHANNELS;
    hello.hello.near_plane = 0.1;
    hello.hello.far_plane = INFINITY;
    strcpy(hello.hello.method, "mvec"); /* extrapolates the engine's motion vectors */
    /* The vectors as an FSR-ready buffer: pixels of the plane, to the previous frame, y down, camera included */
    hello.motion.units = IL_MOTION_PIXELS;
    hello.motion.direction = IL_MOTION_PREVIOUS;
    hello.motion.y_axis = IL_MOTION_Y_DOWN;
    hello.motion.camera = IL_MOTION_CAMERA_INCLUDED;
    hello.motion.missing = IL_MOTION_MISSING_NONE;
    hello.motion.width = MV_WIDTH;
    hello.motion.height = MV_HEIGHT;
    hello.motion.channels = 2;
    hello.motion.format = IL_MOTION_F32;
    hello.motion.scale_x = hello.motion.scale_y = 1.0;
    il_layout_with_motion reply;
    request(IL_MSG_HELLO, &hello, sizeof hello, &reply, sizeof reply);
    const il_layout layout = reply.layout;

    /* Version 3 over a Unix socket: no name, the segment is the descriptor passed with the reply. */
    int shm_fd = layout.shm_name[0] == '\0' ? passed_fd : shm_open(layout.shm_name, O_RDWR, 0);
    if (shm_fd < 0) die("no shared-memory segment");
    unsigned char *shm = mmap(NULL, layout.shm_size, PROT_READ | PROT_WRITE, MAP_SHARED, shm_fd, 0);
    if (shm == MAP_FAILED) die("mmap failed");
    close(shm_fd);

    float *color = (float *)(shm + layout.color_in_offset);
    float *depth = (float *)(shm + layout.depth_offset);
    float *motion = (float *)(shm + reply.motion.motion_offset);
    for (int i = 0; i < WIDTH * HEIGHT; ++i) {
        int x = i % WIDTH;
        color[CHANNELS * i + 0] = (float)x / WIDTH; /* a horizontal ramp */
        color[CHANNELS * i + 1] = 0.25f;
        color[CHANNELS * i + 2] = 0.5f;
        color[CHANNELS * i + 3] = 1.0f;
        depth[i] = 2.0f;
    }
    /* Frame 0: the camera at x = -1 cm, no vectors (il_frame alone, as in version 1). */
    il_submit_with_motion frame = {0};
    frame.frame.frame_id = 0;
    frame.frame.time = 0.0;
    set_pose(&frame.frame, -0.01);
    il_submit_reply submitted;
    request(IL_MSG_SUBMIT, &frame.frame, sizeof frame.frame, &submitted, sizeof submitted);

    /* Frame 1: the camera at x = 0. The wall 2 m away (fx = 50) was 0.25 px further right in frame 0:
     * 0.125 px of the half-resolution plane, to the previous frame, y down. */
    for (uint32_t i = 0; i < reply.motion.width * reply.motion.height; ++i) {
        motion[2 * i + 0] = 0.125f;
        motion[2 * i + 1] = 0.0f;
    }
    frame.frame.frame_id = 1;
    frame.frame.time = 1.0 / 60.0;
    set_pose(&frame.frame, 0.0);
    frame.motion.flags = IL_SUBMIT_VECTORS;
    request(IL_MSG_SUBMIT, &frame, sizeof frame, &submitted, sizeof submitted);

    /* The frame in between: the camera at x = +1 cm. */
    il_frame target = frame.frame;
    target.frame_id = 2;
    target.time = 2.0 / 60.0;
    set_pose(&target, 0.01);
    il_predict_reply predicted;
    request(IL_MSG_PREDICT, &target, sizeof target, &predicted, sizeof predicted);
    const float *out = (const float *)(shm + layout.color_out_offset);
    const unsigned char *holes = shm + layout.holes_offset;
    int centre = (HEIGHT / 2) * WIDTH + WIDTH / 2;
    printf("history=%u method=%s fallback=%u holes=%u centre_red=%.4f centre_hole=%u\n", submitted.history,
           predicted.method, predicted.fallback, predicted.holes, out[CHANNELS * centre], holes[centre]);

    munmap(shm, layout.shm_size);
    request(IL_MSG_BYE, NULL, 0, NULL, 0);
    close(sock_fd);
    return 0;
}
