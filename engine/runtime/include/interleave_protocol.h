/*
 * interleave_protocol.h - wire format of `interleave serve`, protocol versions 1 to 3.
 *
 * The Python side is engine/runtime/protocol.py; tests/runtime/test_server.py compiles this header and checks
 * that every constant, struct size and field offset below matches it. Prose: docs/server.md.
 *
 * Transport: a stream socket (Unix domain socket, or TCP on 127.0.0.1; the server prints the address it
 * listens on as "interleave serve: listening on unix:/path/to.sock" or "... listening on tcp:127.0.0.1:PORT",
 * the port chosen when started with tcp:0). Every message, request or reply,
 * is one il_header followed by header.payload_size bytes. All integers and doubles are little-endian
 * (x86-64 and ARM64 hosts need no conversion); structs are packed by their natural alignment (no
 * padding is implied anywhere: the static asserts below hold on any C11 compiler).
 *
 * Exchange:
 *   HELLO   il_hello            -> il_layout          one session per connection; shared memory created
 *   SUBMIT  il_frame            -> il_submit_reply    colour + depth already written to shared memory
 *   PREDICT il_frame            -> il_predict_reply   colour + holes read back from shared memory
 *   RESET   il_reset            -> il_layout          clear history; a new size moves to a new segment
 *   BYE     (empty)             -> (empty)            the server frees the session and closes
 *
 * Versions: il_header.version is the version a request is written in; its reply carries the same one.
 * Version 1 is the exchange above, unchanged. Version 2 (IL_VERSION) adds motion vectors, each an optional
 * extension appended to the version-1 payload; payload_size says whether it is there:
 *   HELLO   il_hello + il_motion (il_hello_with_motion)   -> il_layout + il_motion_layout
 *   SUBMIT  il_frame + il_submit_motion                   -> il_submit_reply
 *   RESET   il_reset + il_reset_motion                    -> il_layout + il_motion_layout
 * A session opened without il_motion has no motion plane and gets il_layout alone, as in version 1.
 * A version-2 server answers version-1 clients unchanged; a version-1 server answers a version-2 request
 * with IL_BAD_VERSION (and closes), so a client may fall back to version 1 without motion vectors.
 * Version 3 has version 2's messages and sizes; it changes how the segment is reached over a Unix socket
 * (below). A version-2 server answers a version-3 request with IL_BAD_VERSION (and closes): reconnect with 2.
 * A reply has type = request type | IL_MSG_REPLY and echoes request_id. status != IL_OK replies carry
 * UTF-8 error text (not NUL-terminated) as payload. Replies come in request order; requests may be
 * pipelined. After IL_BAD_MAGIC, IL_BAD_VERSION, IL_TOO_LARGE or IL_TRUNCATED the server closes the
 * connection; after any other error the connection stays usable.
 *
 * Shared memory, two kinds, chosen by the HELLO (IL_VERSION_FD and later over a Unix socket, or not):
 *   anonymous (version 3 over a Unix socket): a Linux memfd with no name anywhere, sealed against
 *     shrinking and growing. il_layout.shm_name is "" and the reply that carries the il_layout (HELLO's, and
 *     every RESET's) carries exactly one file descriptor as SCM_RIGHTS ancillary data, attached to the
 *     reply's first byte: read replies with recvmsg() and a control buffer of CMSG_SPACE(sizeof(int)) or
 *     more (read()/recv() would drop it), then mmap(NULL, shm_size, PROT_READ | PROT_WRITE, MAP_SHARED, fd,
 *     0) and close(fd). Each such reply passes the descriptor again (a new one after a size change): unmap
 *     the old mapping. Node.js has no SCM_RIGHTS in its net module: use a native addon (recvmsg) or TCP.
 *   named (TCP; versions 1 and 2 on either socket): il_layout.shm_name is a POSIX name with a leading '/'
 *     for shm_open(name, O_RDWR, 0) + mmap(shm_size); on Linux the segment "/x" is the file /dev/shm/x,
 *     random, mode 0600, unlinked by the server (on BYE, disconnect, a size change, or server shutdown).
 * What each guarantees: a named segment can be opened by any process of the server's user that learns or
 * lists its name (ls /dev/shm). An anonymous one cannot be found by name: it reaches only the client the
 * descriptor is sent to (and to whom that client hands it). Like every open file it remains reachable
 * through /proc/PID/fd of the server or the client to whoever may inspect those processes: root, and
 * processes of the same user (Linux lets a user read its own processes' /proc unless one made itself
 * non-dumpable). Separate users are the boundary; the memfd removes the listing. Images are
 * row-major, row 0 at the top (bottom-up readbacks: set IL_FLAG_FLIP_ROWS), pixels interleaved:
 *   color_in  : height * width * channels, float32 (IL_COLOR_LINEAR, IL_COLOR_SRGB) or uint8 (IL_COLOR_SRGB8)
 *   depth     : height * width float32, in il_hello.depth_convention (IL_DEPTH_LINEAR: planar, engine units)
 *   color_out : like color_in, in il_hello.color_out (alpha, if channels == 4, is 1.0 or 255)
 *   holes     : height * width uint8, 1 where no rendered pixel landed (filled by the hole fill)
 * The server copies color_in / depth during SUBMIT: once the reply arrives they may be overwritten.
 * color_out / holes stay valid until the next request.
 * With a motion plane (version 2), after holes:
 *   motion       : motion_height * motion_width * il_motion.channels, float32 or float16 (il_motion.format);
 *                  the first two channels are the vector's x, y (the RG of an RG/RGB/RGBA texture), in the
 *                  conventions il_motion states; NaN = no vector; rows like the images (IL_FLAG_FLIP_ROWS)
 *   motion_valid : motion_height * motion_width uint8, non-zero where a pixel has a vector (read only when
 *                  il_submit_motion.flags has IL_SUBMIT_VALID)
 * The plane may be smaller than the frame (vectors rendered at a lower resolution): sample (i, j) is what a
 * renderer at motion_width x motion_height writes at its pixel's centre, the frame point
 * ((j + 0.5) * width / motion_width, (i + 0.5) * height / motion_height) in frame pixels whose centres are at
 * +0.5 (at 2x: the corner of four frame pixels); the server reads the depth at that point (interpolated
 * between the frame pixels around it) and gives the vector to the frame pixels of that point's surface.
 * Vectors point into the previously submitted frame: a SUBMIT whose history is reset (first frame, RESET,
 * camera cut, time going backwards) drops them.
 *
 * Matrices: 16 doubles, row-major (m[4 * row + col]) math matrices, unless IL_FLAG_COLUMN_MAJOR (GLM,
 * Unity Matrix4x4, Godot Projection memory order). Per engine (docs/server.md, engine/runtime/session.py):
 *   IL_ENGINE_OPENCV : view = world_to_camera (x right, y down, z forward); projection = K in the top-left 3x3
 *   IL_ENGINE_OPENGL : view = world -> eye (looks down -z); projection = perspective, clip = P * eye
 *   IL_ENGINE_UNITY  : view = camera.worldToCameraMatrix; projection = camera.projectionMatrix
 *   IL_ENGINE_GODOT  : view = camera.get_camera_transform().affine_inverse(); projection = get_camera_projection()
 *   IL_ENGINE_UNREAL : view = the camera's FMatrix (row vectors, translation in row 3) as Unreal stores it;
 *                      projection = FReversedZPerspectiveMatrix / FPerspectiveMatrix as Unreal stores it
 */
#ifndef INTERLEAVE_PROTOCOL_H
#define INTERLEAVE_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#define IL_MAGIC 0x4C544E49u /* "INTL" in memory */
#define IL_VERSION 3     /* the newest version; a request's version is also its reply's */
#define IL_VERSION_MIN 1 /* the oldest version still answered (and the version of replies to bad headers) */
#define IL_VERSION_FD 3  /* from this version on, over a Unix socket, the segment is a memfd passed with the reply */
#define IL_MAX_PAYLOAD 65536
#define IL_MAX_SIDE 16384
#define IL_ALIGNMENT 64

/* il_header.type */
#define IL_MSG_HELLO 1
#define IL_MSG_SUBMIT 2
#define IL_MSG_PREDICT 3
#define IL_MSG_RESET 4
#define IL_MSG_BYE 5
#define IL_MSG_REPLY 0x8000 /* or-ed into the type of every reply */
#define IL_MSG_ERROR 0xFFFF /* reply to a header that could not be read */

/* il_header.status (0 in requests) */
#define IL_OK 0
#define IL_BAD_MAGIC 1   /* connection closed after the reply */
#define IL_BAD_VERSION 2 /* connection closed after the reply */
#define IL_UNKNOWN_TYPE 3
#define IL_BAD_SIZE 4  /* payload_size does not match the type */
#define IL_TOO_LARGE 5 /* payload_size > IL_MAX_PAYLOAD; connection closed after the reply */
#define IL_TRUNCATED 6 /* stream ended inside a message; connection closed after the reply */
#define IL_NO_SESSION 7
#define IL_BAD_INPUT 8 /* NaN pixels, non-rigid pose, unknown method, ...: the text names the frame */
#define IL_NOT_READY 9 /* PREDICT before any SUBMIT since HELLO / RESET */
#define IL_INTERNAL 10
#define IL_OVER_BUDGET 11 /* HELLO / RESET: the session would pass the server's memory budget (--max-memory)
                             or the server is out of file descriptors; connection stays usable: retry later */

/* il_hello.engine */
#define IL_ENGINE_OPENCV 0
#define IL_ENGINE_OPENGL 1
#define IL_ENGINE_UNITY 2
#define IL_ENGINE_UNREAL 3
#define IL_ENGINE_GODOT 4

/* il_hello.depth_convention (engine/conventions/cameras.py, decode_depth_buffer) */
#define IL_DEPTH_OPENGL 0            /* (ndc_z + 1) / 2, near -> 0 */
#define IL_DEPTH_D3D 1               /* ndc_z in [0, 1], near -> 0 */
#define IL_DEPTH_REVERSED 2          /* near -> 1, far -> 0 (0 = sky) */
#define IL_DEPTH_INFINITE 3          /* standard, far = inf */
#define IL_DEPTH_REVERSED_INFINITE 4 /* near / z (Unreal); 0 = sky */
#define IL_DEPTH_LINEAR 5            /* planar depth in engine units; >= far or +inf = sky */
#define IL_DEPTH_LINEAR01 6          /* z / far (Unity Linear01Depth) */

/* il_hello.color_in / color_out */
#define IL_COLOR_LINEAR 0 /* float32 linear-light Rec.709 */
#define IL_COLOR_SRGB 1   /* float32 sRGB-encoded, [0, 1] */
#define IL_COLOR_SRGB8 2  /* uint8 sRGB-encoded */

/* il_hello.flags */
#define IL_FLAG_FLIP_ROWS 1u     /* images are bottom-up (glReadPixels): flipped in and out */
#define IL_FLAG_NDC_Y_DOWN 2u    /* the projection's NDC y points down (Vulkan-style) */
#define IL_FLAG_COLUMN_MAJOR 4u  /* matrices are sent column-major */

/* il_motion codes (version 2). 0 everywhere = the engine's own convention (engine/runtime/session.py):
 *   engine  units   y     direction  camera    missing
 *   unity   UV      up    NEXT       included  none     _CameraMotionVectorsTexture: uv now - uv before
 *   unreal  NDC     up    NEXT       included  camera   DecodeVelocityFromTexture(): ScreenPos now - before;
 *                                                        unwritten (static) pixels: IL_SUBMIT_VALID mask 0
 *   godot   UV      down  PREVIOUS   included  none     velocity texture: prev_uv - uv
 *   opencv  PIXELS  down  PREVIOUS   included  none     Interleave's own Frame.motion_vectors
 *   opengl  (no default: units, y_axis and direction must be given)
 * FSR 2/3 buffers: IL_MOTION_PIXELS, IL_MOTION_PREVIOUS, IL_MOTION_Y_DOWN, scale = motionVectorScale.
 * DLSS (Streamline) buffers: IL_MOTION_UV with scale = mvecScale; camera = cameraMotionIncluded. */
#define IL_MOTION_PIXELS 1   /* il_motion.units: pixels of the motion plane */
#define IL_MOTION_UV 2       /* the viewport spans 1 */
#define IL_MOTION_NDC 3      /* the viewport spans 2 */
#define IL_MOTION_PREVIOUS 1 /* il_motion.direction: from the pixel to where its point was in the previous frame */
#define IL_MOTION_NEXT 2     /* the reverse: previous -> current, the motion since the previous frame */
#define IL_MOTION_Y_DOWN 1   /* il_motion.y_axis: y points down the picture */
#define IL_MOTION_Y_UP 2     /* y points to the top of the picture (NDC y up, UV v = 0 at the bottom) */
#define IL_MOTION_CAMERA_INCLUDED 1 /* il_motion.camera: the vectors include camera motion */
#define IL_MOTION_OBJECT_ONLY 2     /* object motion only: the server adds the camera's */
#define IL_MOTION_MISSING_NONE 1    /* il_motion.missing: a pixel without a vector has none (NaN) */
#define IL_MOTION_MISSING_CAMERA 2  /* it is static: it gets the camera's motion */
#define IL_MOTION_F32 0      /* il_motion.format */
#define IL_MOTION_F16 1

/* il_submit_motion.flags */
#define IL_SUBMIT_VECTORS 1u /* the motion plane holds this frame's vectors */
#define IL_SUBMIT_VALID 2u   /* the motion_valid plane holds their mask (needs IL_SUBMIT_VECTORS) */

/* il_submit_reply.reset */
#define IL_RESET_NONE 0
#define IL_RESET_CAMERA_CUT 1     /* pose jump: history restarted from this frame */
#define IL_RESET_TIME_BACKWARDS 2 /* time not after the newest frame's: history restarted */

/* il_predict_reply.fallback */
#define IL_FALLBACK_NONE 0
#define IL_FALLBACK_HISTORY 1    /* method needs more frames since the start / last reset: reproject used */
#define IL_FALLBACK_CAMERA_CUT 2 /* target pose too far from the newest frame: newest frame repeated */

typedef struct il_header {
    uint32_t magic;        /* IL_MAGIC */
    uint16_t version;      /* IL_VERSION */
    uint16_t type;         /* IL_MSG_* (| IL_MSG_REPLY in replies) */
    uint32_t request_id;   /* chosen by the client, echoed in the reply */
    uint32_t status;       /* 0 in requests; IL_OK or an error code in replies */
    uint64_t payload_size; /* bytes after the header */
} il_header;

typedef struct il_hello {
    uint32_t engine;           /* IL_ENGINE_* */
    uint32_t depth_convention; /* IL_DEPTH_* */
    uint32_t color_in;         /* IL_COLOR_* of submitted colour */
    uint32_t color_out;        /* IL_COLOR_* of predicted colour */
    uint32_t width;            /* pixels, 1..IL_MAX_SIDE */
    uint32_t height;
    uint32_t reserved0;        /* ignored (0; was k): the server follows the times and poses of each PREDICT */
    uint32_t channels;         /* 3 (RGB) or 4 (RGBA; alpha ignored in, 1 out) */
    uint32_t flags;            /* IL_FLAG_* */
    uint32_t reserved;         /* 0 */
    double near_plane;         /* engine units */
    double far_plane;          /* engine units; INFINITY for an infinite far plane */
    double meters_per_unit;    /* 0 = engine default (0.01 Unreal, 1 otherwise) */
    double cut_translation;    /* camera cut: centre moves > this * median depth; 0 = default 0.5 */
    double cut_rotation_deg;   /* camera cut: turns > this; 0 = default 45 */
    char method[64];           /* NUL-terminated predictor name, e.g. "reproject"; "" = reproject */
} il_hello;

typedef struct il_layout {
    char shm_name[64];         /* NUL-terminated POSIX name (leading '/'), or "" for the passed descriptor */
    uint64_t shm_size;         /* bytes to mmap */
    uint64_t color_in_offset;  /* byte offsets, multiples of IL_ALIGNMENT */
    uint64_t depth_offset;
    uint64_t color_out_offset;
    uint64_t holes_offset;
    uint32_t width;            /* frame size the offsets are for */
    uint32_t height;
} il_layout;

typedef struct il_frame {      /* payload of SUBMIT and PREDICT */
    uint64_t frame_id;         /* the client's frame number (named in error text) */
    double time;               /* seconds; SUBMIT times must increase (else history reset) */
    double view[16];
    double projection[16];
} il_frame;

typedef struct il_submit_reply {
    uint64_t frame;            /* the session's number of this frame */
    uint32_t reset;            /* IL_RESET_* */
    uint32_t history;          /* rendered frames the next predictions use */
} il_submit_reply;

typedef struct il_predict_reply {
    uint64_t frame;            /* session number of the newest rendered frame used */
    uint32_t fallback;         /* IL_FALLBACK_* */
    uint32_t holes;            /* number of hole pixels */
    double elapsed_ms;         /* server time for the prediction */
    char method[32];           /* NUL-terminated name of the method used */
} il_predict_reply;

typedef struct il_reset {
    uint32_t width;            /* new size, or 0 to keep */
    uint32_t height;
} il_reset;

/* Version 2: motion vectors. */
typedef struct il_motion {     /* after il_hello in HELLO: the vectors' conventions and plane */
    uint32_t units;            /* IL_MOTION_PIXELS / _UV / _NDC; 0 = the engine's */
    uint32_t direction;        /* IL_MOTION_PREVIOUS / _NEXT; 0 = the engine's */
    uint32_t y_axis;           /* IL_MOTION_Y_DOWN / _Y_UP; 0 = the engine's */
    uint32_t camera;           /* IL_MOTION_CAMERA_INCLUDED / _OBJECT_ONLY; 0 = the engine's */
    uint32_t missing;          /* IL_MOTION_MISSING_NONE / _CAMERA; 0 = the engine's */
    uint32_t width;            /* the motion plane, at most the frame; 0 x 0 = the frame's size */
    uint32_t height;
    uint32_t channels;         /* 2, 3 or 4 per pixel; x, y are the first two */
    uint32_t format;           /* IL_MOTION_F32 / IL_MOTION_F16 */
    uint32_t reserved;         /* 0 */
    double scale_x;            /* applied to the vectors first (FSR motionVectorScale, DLSS mvecScale); 0 = 1 */
    double scale_y;
} il_motion;

typedef struct il_submit_motion { /* after il_frame in SUBMIT */
    uint32_t flags;            /* IL_SUBMIT_*; 0 = this frame has no vectors */
    uint32_t reserved;         /* 0 */
} il_submit_motion;

typedef struct il_reset_motion { /* after il_reset in RESET: the motion plane's new size */
    uint32_t width;            /* 0 x 0 = the frame's size */
    uint32_t height;
} il_reset_motion;

typedef struct il_motion_layout { /* after il_layout, for a session with a motion plane */
    uint64_t motion_offset;       /* byte offsets, multiples of IL_ALIGNMENT */
    uint64_t motion_valid_offset;
    uint32_t width;               /* the plane's size */
    uint32_t height;
} il_motion_layout;

typedef struct il_hello_with_motion { il_hello hello; il_motion motion; } il_hello_with_motion;
typedef struct il_submit_with_motion { il_frame frame; il_submit_motion motion; } il_submit_with_motion;
typedef struct il_reset_with_motion { il_reset reset; il_reset_motion motion; } il_reset_with_motion;
typedef struct il_layout_with_motion { il_layout layout; il_motion_layout motion; } il_layout_with_motion;

/* Every struct size and field offset, as engine/runtime/protocol.py packs them (tests/runtime/test_server.py
 * checks this list against Python). C11 and C++11 use _Static_assert / static_assert; C99 (and C++98) get the
 * same check as a file-scope typedef of an array whose size is -1 when the condition fails, so
 * `gcc -std=c99 -pedantic -Wall -Wextra -Werror` compiles this header and still refuses a wrong layout. */
#if defined(__STDC_VERSION__) && __STDC_VERSION__ >= 201112L
#define IL_STATIC_ASSERT(name, cond, text) _Static_assert(cond, text)
#elif defined(__cplusplus) && __cplusplus >= 201103L
#define IL_STATIC_ASSERT(name, cond, text) static_assert(cond, text)
#else
#define IL_STATIC_ASSERT(name, cond, text) typedef char il_static_assert_##name[(cond) ? 1 : -1]
#endif
#define IL_ASSERT_SIZE(type, size) IL_STATIC_ASSERT(type##_size, sizeof(type) == size, #type " is " #size " bytes")
#define IL_ASSERT_OFFSET(type, field, offset) \
    IL_STATIC_ASSERT(type##_##field, offsetof(type, field) == offset, #type "." #field " is at byte " #offset)

IL_ASSERT_SIZE(il_header, 24); IL_ASSERT_OFFSET(il_header, magic, 0); IL_ASSERT_OFFSET(il_header, version, 4);
IL_ASSERT_OFFSET(il_header, type, 6); IL_ASSERT_OFFSET(il_header, request_id, 8);
IL_ASSERT_OFFSET(il_header, status, 12); IL_ASSERT_OFFSET(il_header, payload_size, 16);
IL_ASSERT_SIZE(il_hello, 144); IL_ASSERT_OFFSET(il_hello, engine, 0); IL_ASSERT_OFFSET(il_hello, depth_convention, 4);
IL_ASSERT_OFFSET(il_hello, color_in, 8); IL_ASSERT_OFFSET(il_hello, color_out, 12);
IL_ASSERT_OFFSET(il_hello, width, 16); IL_ASSERT_OFFSET(il_hello, height, 20);
IL_ASSERT_OFFSET(il_hello, reserved0, 24); IL_ASSERT_OFFSET(il_hello, channels, 28);
IL_ASSERT_OFFSET(il_hello, flags, 32); IL_ASSERT_OFFSET(il_hello, reserved, 36);
IL_ASSERT_OFFSET(il_hello, near_plane, 40); IL_ASSERT_OFFSET(il_hello, far_plane, 48);
IL_ASSERT_OFFSET(il_hello, meters_per_unit, 56); IL_ASSERT_OFFSET(il_hello, cut_translation, 64);
IL_ASSERT_OFFSET(il_hello, cut_rotation_deg, 72); IL_ASSERT_OFFSET(il_hello, method, 80);
IL_ASSERT_SIZE(il_layout, 112); IL_ASSERT_OFFSET(il_layout, shm_name, 0); IL_ASSERT_OFFSET(il_layout, shm_size, 64);
IL_ASSERT_OFFSET(il_layout, color_in_offset, 72); IL_ASSERT_OFFSET(il_layout, depth_offset, 80);
IL_ASSERT_OFFSET(il_layout, color_out_offset, 88); IL_ASSERT_OFFSET(il_layout, holes_offset, 96);
IL_ASSERT_OFFSET(il_layout, width, 104); IL_ASSERT_OFFSET(il_layout, height, 108);
IL_ASSERT_SIZE(il_frame, 272); IL_ASSERT_OFFSET(il_frame, frame_id, 0); IL_ASSERT_OFFSET(il_frame, time, 8);
IL_ASSERT_OFFSET(il_frame, view, 16); IL_ASSERT_OFFSET(il_frame, projection, 144);
IL_ASSERT_SIZE(il_submit_reply, 16); IL_ASSERT_OFFSET(il_submit_reply, frame, 0);
IL_ASSERT_OFFSET(il_submit_reply, reset, 8); IL_ASSERT_OFFSET(il_submit_reply, history, 12);
IL_ASSERT_SIZE(il_predict_reply, 56); IL_ASSERT_OFFSET(il_predict_reply, frame, 0);
IL_ASSERT_OFFSET(il_predict_reply, fallback, 8); IL_ASSERT_OFFSET(il_predict_reply, holes, 12);
IL_ASSERT_OFFSET(il_predict_reply, elapsed_ms, 16); IL_ASSERT_OFFSET(il_predict_reply, method, 24);
IL_ASSERT_SIZE(il_reset, 8); IL_ASSERT_OFFSET(il_reset, width, 0); IL_ASSERT_OFFSET(il_reset, height, 4);
IL_ASSERT_SIZE(il_motion, 56); IL_ASSERT_OFFSET(il_motion, units, 0); IL_ASSERT_OFFSET(il_motion, direction, 4);
IL_ASSERT_OFFSET(il_motion, y_axis, 8); IL_ASSERT_OFFSET(il_motion, camera, 12);
IL_ASSERT_OFFSET(il_motion, missing, 16); IL_ASSERT_OFFSET(il_motion, width, 20);
IL_ASSERT_OFFSET(il_motion, height, 24); IL_ASSERT_OFFSET(il_motion, channels, 28);
IL_ASSERT_OFFSET(il_motion, format, 32); IL_ASSERT_OFFSET(il_motion, reserved, 36);
IL_ASSERT_OFFSET(il_motion, scale_x, 40); IL_ASSERT_OFFSET(il_motion, scale_y, 48);
IL_ASSERT_SIZE(il_submit_motion, 8); IL_ASSERT_OFFSET(il_submit_motion, flags, 0);
IL_ASSERT_OFFSET(il_submit_motion, reserved, 4);
IL_ASSERT_SIZE(il_reset_motion, 8); IL_ASSERT_OFFSET(il_reset_motion, width, 0);
IL_ASSERT_OFFSET(il_reset_motion, height, 4);
IL_ASSERT_SIZE(il_motion_layout, 24); IL_ASSERT_OFFSET(il_motion_layout, motion_offset, 0);
IL_ASSERT_OFFSET(il_motion_layout, motion_valid_offset, 8); IL_ASSERT_OFFSET(il_motion_layout, width, 16);
IL_ASSERT_OFFSET(il_motion_layout, height, 20);
IL_ASSERT_SIZE(il_hello_with_motion, 200);
IL_ASSERT_SIZE(il_submit_with_motion, 280);
IL_ASSERT_SIZE(il_reset_with_motion, 16);
IL_ASSERT_SIZE(il_layout_with_motion, 136);

#endif /* INTERLEAVE_PROTOCOL_H */
