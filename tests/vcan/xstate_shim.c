/*
 * LD_PRELOAD shim for Debian's user-mode-linux 6.1 (linux.uml) on hosts whose
 * XSAVE area is larger than the legacy 832-byte struct _xstate (AVX-512, AMX).
 *
 * UML saves and restores a guest task's FPU state with
 * ptrace(PTRACE_{GET,SET}REGSET, NT_X86_XSTATE) using an 832-byte buffer.  The
 * host kernel accepts short reads but rejects a SETREGSET whose buffer is not
 * exactly the full XSAVE size (EFAULT), so UML panics at its first user
 * process ("userspace - ptrace set fp regs failed, errno = 14").
 *
 * This shim keeps the full host XSAVE image next to each UML buffer (keyed by
 * the buffer's address, which is per guest task): GETREGSET reads the full
 * image and hands UML its 832-byte prefix; SETREGSET lays UML's prefix over
 * the full image and writes that.  Requests with a big enough buffer, and all
 * other ptrace requests, pass through unchanged.  UML issues ptrace from one
 * host thread, so no locking is needed.
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <elf.h>
#include <errno.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ptrace.h>
#include <sys/types.h>
#include <sys/uio.h>

#define PROBE_SIZE (64 * 1024)
#define TABLE_SIZE 4096 /* open addressing; more live guest tasks than this fall back */

typedef long (*ptrace_fn)(int, pid_t, void *, void *);

struct image {
	const void *key;
	unsigned char *data;
};

static struct image table[TABLE_SIZE];
static size_t full_size;

static ptrace_fn real_ptrace(void)
{
	static ptrace_fn fn;

	if (!fn)
		fn = (ptrace_fn)dlsym(RTLD_NEXT, "ptrace");
	return fn;
}

static long regset(int request, pid_t pid, void *buf, size_t len)
{
	struct iovec iov = { .iov_base = buf, .iov_len = len };

	return real_ptrace()(request, pid, (void *)NT_X86_XSTATE, &iov);
}

/* Size of the host's XSAVE regset, learnt from one oversized read. */
static size_t host_size(pid_t pid)
{
	if (!full_size) {
		struct iovec iov = { .iov_base = malloc(PROBE_SIZE), .iov_len = PROBE_SIZE };

		if (iov.iov_base &&
		    real_ptrace()(PTRACE_GETREGSET, pid, (void *)NT_X86_XSTATE, &iov) == 0)
			full_size = iov.iov_len;
		free(iov.iov_base);
	}
	return full_size;
}

/* The full image kept for UML buffer `key`; NULL if it cannot be had. */
static unsigned char *image_for(const void *key, int create)
{
	size_t start = ((uintptr_t)key >> 4) % TABLE_SIZE;

	for (size_t i = 0; i < TABLE_SIZE; i++) {
		struct image *slot = &table[(start + i) % TABLE_SIZE];

		if (slot->key == key)
			return slot->data;
		if (!slot->key) {
			if (!create || !(slot->data = malloc(full_size)))
				return NULL;
			slot->key = key;
			return slot->data;
		}
	}
	return NULL;
}

static long get_xstate(pid_t pid, struct iovec *iov)
{
	unsigned char *full = image_for(iov->iov_base, 1);

	if (!full)
		return regset(PTRACE_GETREGSET, pid, iov->iov_base, iov->iov_len);
	if (regset(PTRACE_GETREGSET, pid, full, full_size) < 0)
		return -1;
	memcpy(iov->iov_base, full, iov->iov_len);
	return 0;
}

static long set_xstate(pid_t pid, const struct iovec *iov)
{
	unsigned char *full = image_for(iov->iov_base, 0);
	unsigned char *scratch = NULL;
	long ret;

	if (!full) {
		/* No saved image (e.g. a freshly copied task): start from the live one. */
		full = scratch = malloc(full_size);
		if (!scratch) {
			errno = ENOMEM;
			return -1;
		}
		if (regset(PTRACE_GETREGSET, pid, scratch, full_size) < 0) {
			free(scratch);
			return -1;
		}
	}
	memcpy(full, iov->iov_base, iov->iov_len);
	ret = regset(PTRACE_SETREGSET, pid, full, full_size);
	free(scratch);
	return ret;
}

long ptrace(enum __ptrace_request request, ...)
{
	va_list ap;
	pid_t pid;
	void *addr, *data;

	va_start(ap, request);
	pid = va_arg(ap, pid_t);
	addr = va_arg(ap, void *);
	data = va_arg(ap, void *);
	va_end(ap);

	if ((request == PTRACE_GETREGSET || request == PTRACE_SETREGSET) &&
	    (uintptr_t)addr == NT_X86_XSTATE && data) {
		struct iovec *iov = data;
		size_t size = host_size(pid);

		if (size && iov->iov_len < size)
			return request == PTRACE_GETREGSET ? get_xstate(pid, iov)
							   : set_xstate(pid, iov);
	}
	return real_ptrace()(request, pid, addr, data);
}
