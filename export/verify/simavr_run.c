/* kf_simavr: run an AVR ELF in simavr and talk to it through three I/O registers.
 *
 * Part of kiloforge (MIT). Built by export/avr.py:  gcc -O2 -o kf_simavr simavr_run.c -lsimavr
 * (Debian: libsimavr-dev). Usage:
 *     kf_simavr [-m atmega328p] [-f 8000000] [-i input.bin] [-o output.bin] [-p paint_from]
 *               [-c max_cycles] firmware.elf
 * Protocol (the AVR side is firmware_templates/avr/kf_sim_io.h):
 *   GPIOR2 (0x4B) read   -> the next byte of input.bin (0 and an "underrun" count when exhausted)
 *   GPIOR1 (0x4A) write  -> one byte appended to output.bin
 *   GPIOR0 (0x3E) write  -> a command: 0xFF ends the run; 0xFE paints the free stack region
 *                           [paint_from, SP] again; 0xFD scans the region painted last and
 *                           prints "S lowest_written_address SP_at_paint"; any other value v is
 *                           a mark: "M v cycle" goes to stdout (the cycle counter then).
 * Stack high-water mark: before the program starts, SRAM from paint_from (the ELF's _end) to
 * RAMEND is filled with 0xA5; at the end the lowest byte that is no longer 0xA5 is reported.
 * The last stdout line: "END state=<simavr state> cycles=<n> stack_low=<addr> underrun=<n>".
 * Exit status: 0 when the program ended with 0xFF, 2 on a crash or timeout, 1 on usage errors.
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <sim_avr.h>
#include <sim_elf.h>
#include <sim_io.h>

#define IO_CMD 0x3E  /* GPIOR0, data-space address */
#define IO_OUT 0x4A  /* GPIOR1 */
#define IO_IN 0x4B   /* GPIOR2 */
#define PAINT 0xA5

static uint8_t *in_buf;
static long in_len, in_pos, underrun;
static FILE *out_f;
static int done;
static uint16_t paint_from, painted_top;

static void paint(avr_t *avr, uint16_t from, uint16_t to)
{
    uint32_t a;
    for (a = from; a <= to && a <= avr->ramend; ++a) {
        avr->data[a] = PAINT;
    }
}

static uint16_t sp_of(avr_t *avr)
{
    return (uint16_t)(avr->data[0x5D] | (avr->data[0x5E] << 8));
}

static void on_cmd(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)param;
    avr->data[addr] = v;
    if (v == 0xFF) {
        done = 1;
        avr->state = cpu_Done;
    } else if (v == 0xFE) {
        if (paint_from) {
            painted_top = sp_of(avr);
            paint(avr, paint_from, painted_top);
        }
    } else if (v == 0xFD) {
        uint32_t a = paint_from, low = (uint32_t)painted_top + 1u;
        for (; paint_from && a <= painted_top; ++a) {
            if (avr->data[a] != PAINT) {
                low = a;
                break;
            }
        }
        printf("S %u %u\n", (unsigned)low, (unsigned)painted_top);
    } else {
        printf("M %u %llu\n", (unsigned)v, (unsigned long long)avr->cycle);
    }
}

static void on_out(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)param;
    avr->data[addr] = v;
    if (out_f) {
        fputc(v, out_f);
    }
}

static uint8_t on_in(avr_t *avr, avr_io_addr_t addr, void *param)
{
    (void)avr;
    (void)addr;
    (void)param;
    if (in_pos < in_len) {
        return in_buf[in_pos++];
    }
    ++underrun;
    return 0;
}

static uint8_t *read_all(const char *path, long *len)
{
    FILE *f = fopen(path, "rb");
    uint8_t *buf;
    if (!f) {
        return NULL;
    }
    fseek(f, 0, SEEK_END);
    *len = ftell(f);
    fseek(f, 0, SEEK_SET);
    buf = malloc(*len > 0 ? (size_t)*len : 1u);
    if (buf && *len > 0 && fread(buf, 1, (size_t)*len, f) != (size_t)*len) {
        free(buf);
        buf = NULL;
    }
    fclose(f);
    return buf;
}

int main(int argc, char **argv)
{
    const char *mcu = "atmega328p", *in_path = NULL, *out_path = NULL, *elf = NULL;
    unsigned long freq = 8000000UL;
    unsigned long long max_cycles = 4000000000ULL;
    elf_firmware_t fw;
    avr_t *avr;
    int i, state = cpu_Running;
    uint32_t a, low;

    for (i = 1; i < argc; ++i) {
        if (!strcmp(argv[i], "-m") && i + 1 < argc) {
            mcu = argv[++i];
        } else if (!strcmp(argv[i], "-f") && i + 1 < argc) {
            freq = strtoul(argv[++i], NULL, 0);
        } else if (!strcmp(argv[i], "-i") && i + 1 < argc) {
            in_path = argv[++i];
        } else if (!strcmp(argv[i], "-o") && i + 1 < argc) {
            out_path = argv[++i];
        } else if (!strcmp(argv[i], "-p") && i + 1 < argc) {
            paint_from = (uint16_t)strtoul(argv[++i], NULL, 0);
        } else if (!strcmp(argv[i], "-c") && i + 1 < argc) {
            max_cycles = strtoull(argv[++i], NULL, 0);
        } else if (argv[i][0] != '-' && !elf) {
            elf = argv[i];
        } else {
            fprintf(stderr, "usage: kf_simavr [-m mcu] [-f hz] [-i in] [-o out] [-p paint_from] [-c max_cycles] fw.elf\n");
            return 1;
        }
    }
    if (!elf) {
        fprintf(stderr, "kf_simavr: no firmware given\n");
        return 1;
    }
    if (in_path && !(in_buf = read_all(in_path, &in_len))) {
        fprintf(stderr, "kf_simavr: cannot read %s\n", in_path);
        return 1;
    }
    if (out_path && !(out_f = fopen(out_path, "wb"))) {
        fprintf(stderr, "kf_simavr: cannot write %s\n", out_path);
        return 1;
    }
    memset(&fw, 0, sizeof(fw));
    if (elf_read_firmware(elf, &fw) != 0) {
        fprintf(stderr, "kf_simavr: cannot load %s\n", elf);
        return 1;
    }
    avr = avr_make_mcu_by_name(mcu);
    if (!avr) {
        fprintf(stderr, "kf_simavr: unknown mcu %s\n", mcu);
        return 1;
    }
    avr_init(avr);
    avr->frequency = freq;
    avr->log = 0;
    avr_load_firmware(avr, &fw);
    avr->frequency = freq;
    avr_register_io_write(avr, IO_CMD, on_cmd, NULL);
    avr_register_io_write(avr, IO_OUT, on_out, NULL);
    avr_register_io_read(avr, IO_IN, on_in, NULL);
    if (paint_from) {
        paint(avr, paint_from, (uint16_t)avr->ramend);
    }
    while (!done) {
        state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed) {
            break;
        }
        if (avr->cycle > max_cycles) {
            break;
        }
    }
    low = avr->ramend + 1u;
    if (paint_from) {
        for (a = paint_from; a <= avr->ramend; ++a) {
            if (avr->data[a] != PAINT) {
                low = a;
                break;
            }
        }
    }
    if (out_f) {
        fclose(out_f);
    }
    printf("END state=%d cycles=%llu stack_low=%u underrun=%ld\n", done ? (int)cpu_Done : state,
           (unsigned long long)avr->cycle, (unsigned)low, underrun);
    return done ? 0 : 2;
}
